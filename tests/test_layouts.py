"""Layouts beyond the square grid (issue 6, modularity): hexagonal cells with three omni wheels, arrays drawn as text
maps (with entries and exits), plain conveyor belts feeding and leaving the array. Checked against the paper's
equations evaluated by hand (literal eq. 19 for the loads), closed forms, and runs that must reach what a field or a
controller asks for."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.config.scenario import MapArray, load_scenario, parse_scenario
from virtual_vehicle.engine.dynamics import ParcelModel
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.model import layout, parcel
from virtual_vehicle.physics.laws import CoulombLaw
from virtual_vehicle.physics.reference import paper_normal_forces
from virtual_vehicle.run.sim import run


def _scenario(array: dict, field=None, control=None, law="stick_slip", duration=2.0, parcels=None, **extra):
    data = {"name": "t", "duration": duration, "array": array, "friction": {"law": law},
            "parcels": parcels or [{"name": "box", "length": 0.4, "width": 0.3, "mass": 2.0, "mu": 0.5,
                                    "x": 0.6, "y": 0.45}], **extra}
    if field is not None:
        data["field"] = field
    if control is not None:
        data["control"] = control
    return parse_scenario(data)


@pytest.mark.parametrize("cells", [layout.grid(7, 5, 0.1, drive_angle=0.3), layout.hexagonal(4, 3, 0.1)])
def test_surface_velocities_sum_each_wheel_along_its_direction(cells):
    """A cell's surface velocity is the sum over its wheels of speed times drive direction, on a turned grid and on
    hexagonal cells (whose wheel directions differ cell to cell)."""
    speeds = np.random.default_rng(0).uniform(-0.5, 0.5, (cells.n, 2))
    got = cells.surface_velocities(speeds)
    u = cells.drive_directions
    assert np.array_equal(got, speeds[:, 0:1] * u[:, 0] + speeds[:, 1:2] * u[:, 1])  # as it was written in place
    np.testing.assert_allclose(got, np.einsum("ik,ikj->ij", speeds, u), rtol=1e-15, atol=1e-17)


def test_hexagonal_lattice_has_six_mutual_neighbours_a_pitch_away_one_per_60_degrees():
    cells = layout.hexagonal(7, 6, 0.1)
    topo = from_layout(cells)
    assert topo.ports == 6
    inner = [j * 7 + i for j in range(1, 5) for i in range(1, 6)]
    for c in inner:
        nb = topo.neighbor[c]
        assert np.all(nb >= 0)
        d = cells.positions[nb] - cells.positions[c]
        np.testing.assert_allclose(np.hypot(d[:, 0], d[:, 1]), 0.1, atol=1e-12)
        np.testing.assert_allclose(np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi), np.deg2rad(60 * np.arange(6)),
                                   atol=1e-9)
        for p, j in enumerate(nb):  # the neighbour's port back leads here
            assert topo.neighbor[j, topo.back_port[c, p]] == c
    assert from_layout(layout.grid(3, 3, 0.1)).ports == 4  # square cells keep four ports


def test_omni_wheels_drive_at_the_projection_of_the_cell_velocity_at_120_degrees():
    cells = layout.hexagonal(2, 2, 0.1, drive_angle=0.3)
    contacts = layout.three_wheels(cells)
    u = contacts.drive_directions[:3, 0]
    angles = (np.arctan2(u[:, 1], u[:, 0]) - 0.3) % (2 * np.pi)
    np.testing.assert_allclose(angles, np.deg2rad([0, 120, 240]), atol=1e-12)
    np.testing.assert_allclose(np.hypot(*(contacts.positions[:3] - cells.positions[0]).T), 0.025, atol=1e-12)
    V = np.array([[0.2, -0.1]] * 4)
    surface = contacts.contact_velocities(V)
    np.testing.assert_allclose(np.einsum("ij,ij->i", surface, contacts.drive_directions[:, 0]),
                               np.einsum("ij,ij->i", V[contacts.cell_of], contacts.drive_directions[:, 0]))
    np.testing.assert_allclose(np.einsum("ij,ij->i", surface, contacts.drive_directions[:, 1]), 0.0, atol=1e-15)


def test_coulomb_force_on_omni_cells_is_eq_22_and_24_summed_over_wheels_with_literal_eq_19_loads():
    cells = layout.hexagonal(12, 12, 0.1)
    contacts = layout.three_wheels(cells)
    spec = parcel.rectangle(0.43, 0.33, mass=2.0, mu=0.5)  # no contact on its outline
    V = np.tile([0.2, 0.0], (cells.n, 1))
    model = ParcelModel(contacts, spec, contacts.contact_velocities(V), CoulombLaw())
    centre = cells.positions[6 * 12 + 5]  # a cell centre: the contacts under the box are mirror-symmetric in x
    y = np.array([centre[0], centre[1], 0.0, 0.0, 0.0, 0.0])
    acc = model.rhs(0.0, y)[3:]
    under = model.support_at(y)
    W = spec.mass * 9.81
    mask = np.zeros(contacts.n, bool)
    mask[under] = True
    N = paper_normal_forces(contacts.positions, mask, centre, W)[under]  # literal eq. 19 with the mask matrix
    assert np.all(N > 0)
    u = contacts.drive_directions[under, 0]
    push = np.sign(u @ [0.2, 0.0])[:, None] * u * (spec.mu * N)[:, None]  # eq. 22 per wheel
    r = contacts.positions[under] - centre
    torque = np.sum(r[:, 0] * push[:, 1] - r[:, 1] * push[:, 0])  # eq. 24
    np.testing.assert_allclose(acc[:2] * spec.mass, push.sum(axis=0), atol=1e-9)
    np.testing.assert_allclose(acc[2] * spec.inertia, torque, atol=1e-9)
    assert abs(acc[1]) < 1e-9  # mirror symmetry: no sideways force
    assert 0.5 * spec.mu * 9.81 < acc[0] < spec.mu * 9.81  # between the worst and best wheel alignment


@pytest.mark.parametrize("deg", [0, 45, 100, 200, 290])
def test_omni_cells_carry_a_parcel_at_the_field_velocity_in_any_direction(deg):
    v = 0.15 * np.array([np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))])
    sc = _scenario({"kind": "hex", "nx": 16, "ny": 14, "pitch": 0.1}, {"kind": "uniform", "velocity": v.tolist()},
                   duration=1.5, parcels=[{"name": "box", "length": 0.4, "width": 0.3, "mass": 2.0, "mu": 0.5,
                                           "x": 0.75, "y": 0.55}])
    tr = run(sc.build()).parcels[0].trajectory
    assert tr.status != "tipped"
    np.testing.assert_allclose(tr.states[-1, 3:5], v, atol=1e-9)  # sticks: exactly the wheels' velocity
    assert abs(tr.states[-1, 5]) < 1e-9


@pytest.mark.parametrize("central", [True, False])
def test_pose_control_from_sensors_on_hexagonal_omni_cells(central):
    sc = _scenario({"kind": "hex", "nx": 20, "ny": 22, "pitch": 0.05},
                   control={"program": "pose", "central": central, "period": 0.02, "speed": 0.2, "gain": 3.0,
                            "targets": [[0.62, 0.55, -0.3]]},
                   duration=3.0, parcels=[{"name": "carton", "length": 0.2, "width": 0.15, "mass": 1.0, "mu": 0.8,
                                           "x": 0.3, "y": 0.3, "theta": 0.2}])
    end = run(sc.build()).parcels[0].trajectory.states[-1]
    assert np.hypot(end[0] - 0.62, end[1] - 0.55) < 5e-3 and abs(end[2] + 0.3) < np.deg2rad(2)


def test_a_belt_holds_a_parcel_sideways_like_the_viscous_closed_form():
    """On a belt alone, the viscous law (eq. 33) gives v(t) = V + (v0 - V) exp(-mu g t) with V the belt's surface
    velocity (along it, zero across)."""
    mu, g = 0.8, 9.81
    sc = _scenario({"kind": "grid", "nx": 3, "ny": 3, "pitch": 0.1, "origin": [3.0, 0.0],
                    "belts": [{"start": [0.0, 0.0], "end": [2.5, 0.0], "width": 0.4, "speed": 0.3}]},
                   {"kind": "uniform", "velocity": [0.0, 0.5]}, law="viscous", duration=0.5,
                   parcels=[{"name": "box", "length": 0.3, "width": 0.2, "mass": 2.0, "mu": mu, "x": 0.5,
                             "y": 0.0, "vx": 0.0, "vy": 0.2}], output_dt=0.05)
    setup = sc.build()
    belt = setup.cells.n - 1
    assert setup.cells.belts.tolist() == [False] * 9 + [True] and setup.cells.ports[belt] == 0
    np.testing.assert_allclose(setup.velocities[belt], [0.3, 0.0])  # the field does not steer a plain belt
    assert np.all(setup.velocities[:9] == [0.0, 0.5])
    tr = run(setup).parcels[0].trajectory
    decay = np.exp(-mu * g * tr.times)
    np.testing.assert_allclose(tr.states[:, 3], 0.3 * (1 - decay), atol=1e-8)
    np.testing.assert_allclose(tr.states[:, 4], 0.2 * decay, atol=1e-8)


def test_belts_feed_the_array_and_take_parcels_away():
    sc = _scenario({"kind": "map", "pitch": 0.1, "origin": [1.0, 0.0], "map": "oooooooo\n" * 5,
                    "belts": [{"start": [0.0, 0.2], "end": [0.92, 0.2], "width": 0.4, "speed": 0.3},
                              {"start": [1.78, 0.2], "end": [2.8, 0.2], "width": 0.4, "speed": 0.3}]},
                   {"kind": "uniform", "velocity": [0.3, 0.0]}, duration=6.0,
                   parcels=[{"name": "box", "length": 0.3, "width": 0.25, "mass": 2.0, "mu": 0.5, "x": 0.3,
                             "y": 0.2}])
    res = run(sc.build())
    tr = res.parcels[0].trajectory
    assert tr.states[-1, 0] > 1.9  # on the second belt
    np.testing.assert_allclose(tr.states[-1, 3:6], [0.3, 0.0, 0.0], atol=1e-9)


def test_a_belt_may_not_cover_cells_and_belts_need_a_length():
    with pytest.raises(ScenarioError, match=r"array\.belts\[0\].*covers cell"):
        _scenario({"kind": "grid", "nx": 5, "ny": 5, "pitch": 0.1,
                   "belts": [{"start": [0.0, 0.2], "end": [1.0, 0.2], "width": 0.2, "speed": 0.3}]},
                  {"kind": "uniform", "velocity": [0.1, 0.0]}).build()
    with pytest.raises(ScenarioError, match="distinct start and end"):
        _scenario({"kind": "grid", "nx": 5, "ny": 5, "pitch": 0.1,
                   "belts": [{"start": [2.0, 0.2], "end": [2.0, 0.2], "width": 0.2, "speed": 0.3}]},
                  {"kind": "uniform", "velocity": [0.1, 0.0]}).build()


MIXED = {"kind": "mixed", "parts": [{"kind": "grid", "nx": 8, "ny": 6, "pitch": 0.1},
                                    {"kind": "hex", "nx": 8, "ny": 7, "pitch": 0.1, "origin": [0.8, 0.0]}]}


def test_a_mixed_array_joins_square_and_hexagonal_cells_that_talk_and_carry_across_the_seam():
    sc = _scenario(MIXED, {"kind": "uniform", "velocity": [0.2, 0.0]}, duration=4.0,
                   parcels=[{"name": "box", "length": 0.3, "width": 0.25, "mass": 2.0, "mu": 0.5, "x": 0.3,
                             "y": 0.25}])
    setup = sc.build()
    cells, contacts = setup.cells, setup.contact_layer
    assert cells.n == 48 + 56 and contacts.n == 48 + 3 * 56
    assert cells.ports[:48].tolist() == [4] * 48 and cells.ports[48:].tolist() == [6] * 56
    topo = from_layout(cells)
    assert topo.neighbor[7, 0] == 48 and topo.neighbor[48, 3] == 7  # the first rows meet: east <-> west
    a, p = np.nonzero(topo.connected)
    across = (a < 48) != (topo.neighbor[a, p] < 48)
    assert across.sum() >= 2 * 5  # links across the seam, both ways (rows of 0.1 and 0.0866 m meet unevenly)
    assert np.all(topo.neighbor[topo.neighbor[a, p], topo.back_port[a, p]] == a)
    tr = run(setup).parcels[0].trajectory
    assert tr.states[-1, 0] > 1.0  # well onto the hexagonal part
    np.testing.assert_allclose(tr.states[-1, 3:6], [0.2, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("parts, message", [
    ([{"kind": "grid", "nx": 2, "ny": 2, "pitch": 0.1}, {"kind": "grid", "nx": 2, "ny": 2, "pitch": 0.2,
                                                          "origin": [1.0, 0.0]}], r"array\.parts\[1\]\.pitch"),
    ([{"kind": "grid", "nx": 2, "ny": 2, "pitch": 0.1}, {"kind": "grid", "nx": 2, "ny": 2, "pitch": 0.1}],
     "the parts overlap"),
    ([{"kind": "grid", "nx": 2, "ny": 2, "pitch": 0.1,
       "belts": [{"start": [1.0, 0.0], "end": [2.0, 0.0], "width": 0.2, "speed": 0.1}]}], "not on its parts"),
])
def test_bad_mixed_arrays_are_named(parts, message):
    parcels = [{"name": "box", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 0.5, "x": 0.05, "y": 0.05}]
    with pytest.raises(ScenarioError, match=message):
        _scenario({"kind": "mixed", "parts": parts}, {"kind": "uniform", "velocity": [0.1, 0.0]},
                  parcels=parcels).build()


SORTING_JUNCTION_MAP = """
oooooooooooooo2222oooooo
oooooooooooooo2222oo0000
oooooooooooooo2222oo0000
oooooooooooooooooooo0000
EEEooooooooooooooooo0000
EEEooooooooooooooooooooo
EEEooooooooooooooooooooo
EEEooooooooooooooooo1111
oooooooooooooooooooo1111
oooooooooooooooooooo1111
oooooooooooooooooooo1111
oooooooooooooooooooooooo
"""


def test_a_map_draws_the_array_and_marks_the_sorters_entries_and_exits():
    """The bundled sorting junction drawn as a map instead of a grid with outlines runs the same, bit for bit."""
    sc, _ = load_scenario("sorting_junction")
    sc = sc.model_copy(update={"duration": 12.0})
    control = sc.control.model_copy(update={"entries": [], "exits": []})
    drawn = sc.model_copy(update={"array": MapArray(kind="map", pitch=0.1, map=SORTING_JUNCTION_MAP),
                                  "control": control})
    a, b = sc.build(), drawn.build()
    np.testing.assert_array_equal(a.cells.positions, b.cells.positions)
    for key in ("entry", "exit", "exit_port"):
        np.testing.assert_array_equal(a.control.config[key], b.control.config[key])
    ra, rb = run(a), run(b)
    for pa, pb in zip(ra.parcels, rb.parcels):
        np.testing.assert_array_equal(pa.trajectory.states, pb.trajectory.states)
    so = rb.summary()["sorting"]
    assert so["correct"] >= 2 and so["misrouted"] == 0 and so["collisions"] == 0


@pytest.mark.parametrize("array, control, message", [
    ({"kind": "map", "pitch": 0.1, "map": "ooo\noxo"}, None, "unknown character 'x' on line 2, column 2"),
    ({"kind": "map", "pitch": 0.1, "map": "...\n   "}, None, "the map has no cells"),
    ({"kind": "map", "pitch": 0.1, "map": "Eoo1\nEooo"}, {"program": "sort"}, "mark them 0, 1"),
    ({"kind": "map", "pitch": 0.1, "map": "ooo0\nooo0"}, {"program": "sort"}, "mark entry cells E"),
    ({"kind": "map", "pitch": 0.1, "lattice": "hex", "map": "Eoo0\nEoo0"}, {"program": "sort"}, "where the rows end"),
    ({"kind": "map", "pitch": 0.1, "lattice": "hex", "wheels": "separate", "map": "oo\noo"}, None, "three omni"),
    ({"kind": "grid", "nx": 4, "ny": 4, "pitch": 0.1}, {"program": "sort"}, "needs exits"),
])
def test_bad_maps_are_named(array, control, message):
    parcels = [{"name": "box", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 0.5, "x": 0.1, "y": 0.05}]
    field = None if control else {"kind": "uniform", "velocity": [0.1, 0.0]}
    with pytest.raises(ScenarioError, match=message):
        _scenario(array, field, control, parcels=parcels).build()


def test_hexagonal_cells_refuse_the_viscous_law_and_wheel_faults():
    hexa = {"kind": "hex", "nx": 8, "ny": 8, "pitch": 0.1}
    with pytest.raises(ScenarioError, match="viscous law"):
        _scenario(hexa, {"kind": "uniform", "velocity": [0.1, 0.0]}, law="viscous").build()
    with pytest.raises(ScenarioError, match="whole-cell faults"):
        _scenario(hexa, {"kind": "uniform", "velocity": [0.1, 0.0]}, faults={"stuck_wheels": [[3, 1]]}).build()


def test_a_free_wheel_of_a_separate_wheel_cell_frees_only_that_wheel():
    sc = _scenario({"kind": "grid", "nx": 8, "ny": 8, "pitch": 0.1, "wheels": "separate"},
                   {"kind": "uniform", "velocity": [0.1, 0.1]}, faults={"free_wheels": [[9, 0]]})
    active = sc.build().contact_layer.wheel_active
    assert active[18].tolist() == [False, False]  # wheel 0 of cell 9: no traction left
    assert active[19].tolist() == [True, False]  # wheel 1 of cell 9 still drives
    assert active.sum() == 2 * 64 - 1


def test_cell_outlines_tile_the_floor_and_pictures_draw_belts_and_hexagons(tmp_path):
    import shapely

    from virtual_vehicle.ui.viz import plot_paths

    sc = _scenario({**MIXED, "belts": [{"start": [-1.0, 0.25], "end": [-0.08, 0.25], "width": 0.3, "speed": 0.2}]},
                   {"kind": "uniform", "velocity": [0.2, 0.0]}, duration=0.2,
                   parcels=[{"name": "box", "length": 0.3, "width": 0.25, "mass": 2.0, "mu": 0.5, "x": 0.3,
                             "y": 0.25}])
    setup = sc.build()
    outlines = layout.cell_outlines(setup.cells, setup.contact_layer)
    areas = np.array([shapely.Polygon(o).area for o in outlines])
    np.testing.assert_allclose(areas[:48], 0.01)  # squares of side pitch
    np.testing.assert_allclose(areas[48:104], np.sqrt(3) / 2 * 0.01)  # hexagons of apothem pitch / 2
    np.testing.assert_allclose(areas[104], 0.92 * 0.3)  # the belt: its length by its width
    hexes = shapely.union_all([shapely.Polygon(o) for o in outlines[48:104]])
    assert hexes.area == pytest.approx(56 * np.sqrt(3) / 2 * 0.01)  # hexagons tile without overlap
    fig = plot_paths(run(setup), tmp_path / "paths.png")
    assert any(p.get_label() == "belt" for p in fig.axes[0].patches)
    assert (tmp_path / "paths.png").stat().st_size > 10_000


def test_the_hybrid_junction_sorts_from_a_feed_belt_onto_exit_belts():
    """The bundled hybrid hall: a plain belt feeds the junction, exit lanes hand parcels to plain belts. A parcel
    is delivered when its lane hands it over (it then rides the belt to its end and falls off, which is no loss)."""
    sc, _ = load_scenario("hybrid_junction")
    res = run(sc.model_copy(update={"duration": 26.0}).build())
    summary = res.summary()
    so = summary["sorting"]
    assert so["correct"] >= 4 and so["misrouted"] == 0 and so["lost"] == 0 and so["collisions"] == 0
    right, top = res.setup.cells.positions[~res.setup.cells.belts].max(axis=0)
    handed_over = [p for p, pr in zip(summary["parcels"], res.parcels)  # now beyond the cells, on an exit belt
                   if pr.trajectory.states[-1, 0] > right + 0.1 or pr.trajectory.states[-1, 1] > top + 0.1]
    assert len(handed_over) >= 4 and all(p["outcome"] == "delivered" and p["correct"] for p in handed_over)


def test_a_parcel_that_falls_off_the_feed_belt_before_the_cells_is_lost():
    sc, _ = load_scenario("hybrid_junction")
    feed = sc.array.belts[0].model_copy(update={"speed": -0.3})  # run the feed backwards: off its far end
    array = sc.array.model_copy(update={"belts": [feed, *sc.array.belts[1:]]})
    res = run(sc.model_copy(update={"duration": 3.0, "array": array, "parcels": sc.parcels[:1]}).build())
    assert res.parcels[0].trajectory.status == "tipped"
    assert res.summary()["sorting"]["lost"] == 1


def test_a_destination_beyond_the_maps_exits_is_named():
    parcels = [{"name": "box", "length": 0.15, "width": 0.15, "mass": 1.0, "mu": 0.5, "x": 0.1, "y": 0.25,
                "destination": 1}]
    with pytest.raises(ScenarioError, match=r"parcels\[0\]\.destination.*1 exits, 0\.\.0"):
        _scenario({"kind": "map", "pitch": 0.1, "map": "oooooo\nEEooo0\nEEooo0\noooooo"}, control={"program": "sort"},
                  law="viscous", parcels=parcels).build()
