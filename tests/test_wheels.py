"""Two wheels per cell as separate contacts, against the paper's lumped cell."""

import numpy as np
import pytest

from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.run.sim import run

D = 0.1


def test_contact_layer_geometry_and_velocities():
    cells = layout.grid(2, 1, D, drive_angle=np.pi / 2)
    c = layout.separate_wheels(cells)
    assert c.n == 4 and c.separate and c.cell_of.tolist() == [0, 0, 1, 1]
    # wheel 0 of cell 0 at (0, -pitch/4) in the cell frame, whose x axis is the world's +y
    np.testing.assert_allclose(c.positions[0], [D / 4, 0.0], atol=1e-15)
    np.testing.assert_allclose(c.drive_directions[1, 0], [-1, 0], atol=1e-15)  # wheel 1 drives along the cell's y
    V = c.contact_velocities(np.array([[0.3, 0.4], [0.0, -0.2]]))
    np.testing.assert_allclose(V[0], [0.0, 0.4], atol=1e-15)  # wheel 0 keeps the world-y part
    np.testing.assert_allclose(V[1], [0.3, 0.0], atol=1e-15)
    with pytest.raises(ValueError, match="different points"):
        layout.separate_wheels(cells, [[0, 0], [0, 0]])


def wrench(cells, field, X, law=None):
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.5)
    m = ParcelModel(cells, spec, cells.contact_velocities(field.velocities(layout.grid(2, 2, D, (-D / 2, -D / 2)))),
                    law or laws.CoulombLaw())
    y = np.array([*X, 0.0, 0, 0, 0])
    d = m.piece_at(y).rhs(0, y)
    return d[3:5] * spec.mass, d[5] * spec.inertia


def test_separate_wheels_halve_the_papers_force_and_can_twist():
    """Each wheel carries about half its cell's load, so the paper's lumped model (each wheel pushing with mu N of
    the whole cell) gives twice the force; and offset wheels make a torque where the lumped 2x2 field has none."""
    cells = layout.grid(2, 2, D, origin=(-D / 2, -D / 2))
    field = fields.Inward((0, 0), 0.5)
    X = (0.012, -0.007)
    f_lumped, tau_lumped = wrench(cells, field, X)
    tiny = layout.separate_wheels(cells, [[0, -1e-7], [-1e-7, 0]])
    f_tiny, _ = wrench(tiny, field, X)
    np.testing.assert_allclose(f_tiny, 0.5 * f_lumped, rtol=1e-4)
    assert abs(tau_lumped) < 1e-12
    # at quarter-pitch offsets the wheels also move the load and the field's centre: force and torque both depart
    f_sep, tau_sep = wrench(layout.separate_wheels(cells), field, X)
    assert abs(tau_sep) > 1e-3
    assert np.abs(f_sep - 0.5 * f_lumped).max() > 0.1 * np.abs(f_lumped).max()


def test_stick_slip_on_separate_wheels_rides_at_wheel_speed():
    cells = layout.grid(20, 6, D)
    c = layout.separate_wheels(cells)
    spec = parcel.rectangle(0.35, 0.25, 1.0, 0.5)
    m = ParcelModel(c, spec, c.contact_velocities(fields.Uniform((0.3, 0.0)).velocities(cells)), laws.StickSlipLaw())
    tr = integrate(m, [0.3, 0.25, 0.0, 0.0, 0.05, 0.0], 0, 0.6, dt=1e-3)
    np.testing.assert_allclose(tr.states[-1, 3:], [0.3, 0.0, 0.0], atol=1e-9)  # stuck: x at wheel speed, y held


def test_scenario_option_and_its_limits():
    sc, _ = load_scenario("paper_2x2_inward")
    d = sc.model_dump()
    d["array"]["wheels"] = "separate"
    lumped = run(sc.build()).parcels[0].trajectory
    separate = run(parse_scenario(d).build()).parcels[0].trajectory
    assert separate.status == "completed"
    assert np.abs(separate.states[:, 2] - lumped.states[:, 2]).max() > 1e-4  # the separate wheels turn it
    d["friction"]["law"] = "viscous"
    with pytest.raises(ScenarioError, match="array.wheels"):
        parse_scenario(d).build()


def test_start_check_uses_the_contact_layer():
    """A small parcel balanced on one cell centre rests on a lumped cell, but with separate wheels nothing is under
    its centre of mass: the scenario must be rejected."""
    from test_cli import base

    d = base()
    d["parcels"][0].update(length=0.12, width=0.12, x=0.1, y=0.1)
    d["friction"]["law"] = "coulomb"
    parse_scenario(d).build()
    d["array"]["wheels"] = "separate"
    with pytest.raises(ScenarioError, match="cannot rest"):
        parse_scenario(d).build()
