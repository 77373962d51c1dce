"""Field library, field design and equilibria (paper Section 5): checked against the paper's 2x2 inward field, the
law's own wrench, brute force, and simulation."""

import itertools

import numpy as np
import pytest

from virtual_vehicle.analysis.equilibria import equilibria
from virtual_vehicle.cells.design import twist_design, wrench_design, wrench_matrix
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws

G = 9.81


def test_field_library_shapes():
    cells = layout.grid(5, 5, 0.1)
    rot = fields.Rotation((0.2, 0.2), 2.0).velocities(cells)
    r = cells.positions - 0.2
    np.testing.assert_allclose(np.einsum("ij,ij->i", rot, r), 0, atol=1e-15)  # tangential
    np.testing.assert_allclose(np.hypot(*rot.T), 2.0 * np.hypot(*r.T), rtol=1e-12)
    rad = fields.Radial((0.2, 0.2), 0.3).velocities(cells)
    off = np.hypot(*r.T) > 0
    np.testing.assert_allclose(np.hypot(*rad[off].T), 0.3)
    np.testing.assert_allclose(np.einsum("ij,ij->i", rad[off], -r[off]) / np.hypot(*r[off].T), 0.3)
    assert np.all(rad[~off] == 0)
    sq = fields.Squeeze((0.0, 0.2), (1.0, 0.0), 0.1, along=0.05).velocities(cells)
    np.testing.assert_allclose(sq[:, 0], 0.05)
    np.testing.assert_allclose(sq[:, 1], -0.1 * np.sign(cells.positions[:, 1] - 0.2))
    tw = fields.Twist((0.1, 0.1), (0.1, -0.2, 0.5)).velocities(cells)
    np.testing.assert_allclose(tw, fields.Uniform((0.1, -0.2)).velocities(cells)
                               + fields.Rotation((0.1, 0.1), 0.5).velocities(cells), atol=1e-15)
    reg = fields.Regions((([[0, 0], [0.2, 0], [0.2, 0.4], [0, 0.4]], fields.Uniform((1.0, 0.0))),),
                         fields.Uniform((0.0, 1.0))).velocities(cells)
    left = cells.positions[:, 0] <= 0.2
    assert np.all(reg[left] == [1.0, 0.0]) and np.all(reg[~left] == [0.0, 1.0])


def test_regions_in_a_scenario_file():
    sc = parse_scenario({
        "duration": 1.0, "array": {"kind": "grid", "nx": 10, "ny": 4, "pitch": 0.1},
        "field": {"kind": "regions", "default": {"kind": "uniform", "velocity": [0.1, 0.0]},
                  "regions": [{"outline": [[0.5, -1], [2, -1], [2, 1], [0.5, 1]],
                               "field": {"kind": "rotation", "center": [0.7, 0.15], "omega": 1.0}}]},
        "parcels": [{"name": "a", "length": 0.2, "width": 0.2, "mass": 1.0, "mu": 0.5, "x": 0.2, "y": 0.15}]})
    setup = sc.build()
    right = setup.cells.positions[:, 0] >= 0.5
    np.testing.assert_allclose(setup.velocities[~right], [[0.1, 0.0]] * int((~right).sum()))
    np.testing.assert_allclose(setup.velocities[right], fields.Rotation((0.7, 0.15), 1.0).velocities(setup.cells)[right])


STATE = np.array([0.45, 0.45, 0.1, 0.05, -0.02, 0.2])


def model_wrench(cells, spec, design, law, state):
    m = ParcelModel(cells, spec, design.velocities, law, G)
    return m.rhs(0.0, state)[3:] * [spec.mass, spec.mass, spec.inertia]


def test_viscous_wrench_design_is_exact_when_feasible():
    cells = layout.grid(10, 10, 0.1)
    spec = parcel.rectangle(0.35, 0.3, 2.0, 0.5)
    law = laws.ViscousLaw()
    rng = np.random.default_rng(3)
    for _ in range(5):  # a wrench some wheel speeds within the limit produce is reproduced exactly
        speeds = rng.uniform(-0.4, 0.4, size=(cells.n, 2))
        v = np.einsum("ik,ikj->ij", speeds, cells.drive_directions)
        target = ParcelModel(cells, spec, v, law, G).rhs(0, STATE)[3:] * [spec.mass, spec.mass, spec.inertia]
        d = wrench_design(cells, spec, STATE, target, law, vmax=0.5)
        assert d.residual < 1e-9
        np.testing.assert_allclose(model_wrench(cells, spec, d, law, STATE), target, atol=1e-9)
        assert np.abs(d.wheel_speeds).max() <= 0.5 + 1e-12


def test_coulomb_wrench_design_is_the_best_spin_pattern():
    cells = layout.grid(2, 2, 0.1)
    spec = parcel.rectangle(0.3, 0.3, 1.0, 0.5)
    state = np.array([0.05, 0.05, 0.0, 0, 0, 0])
    A, support, _ = wrench_matrix(cells, spec, state)
    for target in ([0.0, 0.0, 0.2], [3.0, -1.0, 0.0], [10.0, 10.0, 0.0]):
        d = wrench_design(cells, spec, state, target, laws.CoulombLaw(), vmax=0.3)
        brute = min(np.linalg.norm(A @ np.array(s) - target) for s in itertools.product((-1, 0, 1), repeat=8))
        assert abs(d.residual - brute) < 1e-12
        np.testing.assert_allclose(model_wrench(cells, spec, d, laws.CoulombLaw(), state), d.achieved, atol=1e-12)


def test_twist_design_is_the_viscous_steady_state():
    """A parcel already moving with the requested twist feels no force from the designed wheels (viscous law)."""
    cells = layout.grid(30, 30, 0.05)
    spec = parcel.rectangle(0.3, 0.2, 1.5, 0.8)
    want = (0.05, 0.02, 0.3)
    state = np.array([0.75, 0.75, 0.2, *want])
    d = twist_design(cells, spec, state, want)
    assert d.scale == 1.0
    np.testing.assert_allclose(model_wrench(cells, spec, d, laws.ViscousLaw(), state), 0, atol=1e-12)
    limited = twist_design(cells, spec, state, want, vmax=0.04)
    assert limited.scale < 1 and np.abs(limited.wheel_speeds).max() <= 0.04 + 1e-15
    # Released at rest, the parcel converges to the twist when it is one a free rigid body can keep: a
    # translation, or a spin about its own centre of mass (a rotation about another point needs a centripetal
    # force, hence slip: the design is instantaneous and is re-made every control tick).
    for twist in ((0.05, 0.02, 0.0), (0.0, 0.0, 0.3)):
        field = fields.Twist((0.75, 0.75), twist).velocities(cells)
        tr = integrate(ParcelModel(cells, spec, field, laws.ViscousLaw(), G), [0.75, 0.75, 0.2, 0, 0, 0], 0, 3.0)
        np.testing.assert_allclose(tr.states[-1, 3:], twist, atol=1e-9)


def test_paper_2x2_inward_field_equilibrium():
    """Paper 4.3 example: the 2x2 inward field has its equilibrium at the centre with a = -(2 mu W / d) I and zero
    torque at every heading (neutral), undamped under the Coulomb law (marginal: the parcel oscillates)."""
    d, mu, W = 0.1, 0.5, 1.0 * G
    cells = layout.grid(2, 2, d)
    spec = parcel.rectangle(0.3, 0.3, 1.0, mu)
    v = fields.Inward((0.05, 0.05), 0.2).velocities(cells)
    eqs = equilibria(cells, spec, v, laws.CoulombLaw(), bounds=(0.0, 0.0, 0.1, 0.1),
                     headings=np.linspace(0, np.pi / 2, 10), step=0.01)
    assert len(eqs) == 1
    e = eqs[0]
    np.testing.assert_allclose(e.pose[:2], [0.05, 0.05], atol=1e-12)
    np.testing.assert_allclose(e.stiffness, 2 * mu * W / d * np.eye(2), atol=1e-9)
    assert e.rotation == "neutral" and e.heading_range == (0.0, np.pi / 2)
    assert e.translation == "marginal" and e.stable


@pytest.mark.parametrize("start", [(0.26, 0.24, 0.45), (0.22, 0.27, 0.55), (0.27, 0.26, 1.3), (0.23, 0.23, 2.6)])
def test_released_parcels_settle_where_the_analysis_says(start):
    cells = layout.grid(6, 6, 0.1)
    spec = parcel.rectangle(0.35, 0.2, 1.0, 0.5)
    v = fields.Inward((0.25, 0.25), 0.2).velocities(cells)
    law = laws.ViscousLaw()
    eqs = equilibria(cells, spec, v, law, bounds=(0.15, 0.15, 0.35, 0.35), headings=np.linspace(0, 2 * np.pi, 73),
                     step=0.025)
    assert any(e.rotation == "unstable" for e in eqs) and any(e.rotation == "stable" for e in eqs)
    tr = integrate(ParcelModel(cells, spec, v, law, G), [*start, 0, 0, 0], 0, 8.0)
    x, y, th, *vel = tr.states[-1]
    assert np.abs(vel).max() < 1e-7  # at rest
    th = th % (2 * np.pi)

    def holds(e):
        lo, hi = e.heading_range or (e.pose[2], e.pose[2])
        return (np.hypot(x - e.pose[0], y - e.pose[1]) < 1e-6 and lo - 1e-6 <= th <= hi + 1e-6
                and e.rotation != "unstable")

    assert any(holds(e) for e in eqs), (tr.states[-1], [(e.pose, e.rotation, e.heading_range) for e in eqs])


def test_equilibria_command(tmp_path):
    import json

    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["equilibria", "paper_2x2_inward", "-o", str(tmp_path), "--headings", "9",
                              "--step", "0.01"])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "equilibria.json").read_text())
    assert any(abs(e["x_m"]) < 1e-9 and abs(e["y_m"]) < 1e-9 and e["rotation"] == "neutral" for e in data["equilibria"])
    assert (tmp_path / "force_field.png").stat().st_size > 10_000
    res = runner.invoke(app, ["equilibria", "paper_2x2_inward", "--parcel", "nope", "-o", str(tmp_path)])
    assert res.exit_code == 2 and "nope" in res.output
    res = runner.invoke(app, ["equilibria", "prototype_18_network", "-o", str(tmp_path)])
    assert res.exit_code == 2 and "field" in res.output
