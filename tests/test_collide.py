"""Parcels among parcels: geometry against shapely, collisions against textbook mechanics (momentum, inelastic
impact, a pushed pair), no interpenetration, and runs whose parcels never meet left exactly as they were."""

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.engine.plant import Integration, Plant
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import polygon, rectangle
from virtual_vehicle.physics.collide import ContactParams, outline_distance, overlap_area, pair_contacts
from virtual_vehicle.physics.laws import LAWS
from virtual_vehicle.run.sim import run

G = 9.81
L_SHAPE = [[0, 0], [0.3, 0], [0.3, 0.15], [0.15, 0.15], [0.15, 0.3], [0, 0.3]]


def momentum(plant, ys):
    """Total linear momentum (kg m/s) and angular momentum about the origin (kg m^2/s)."""
    p = np.zeros(2)
    L = 0.0
    for spec, y in zip(plant.specs, ys):
        p += spec.mass * y[3:5]
        L += spec.mass * (y[0] * y[4] - y[1] * y[3]) + spec.inertia * y[5]
    return p, L


def kinetic(plant, ys):
    return sum(0.5 * s.mass * (y[3] ** 2 + y[4] ** 2) + 0.5 * s.inertia * y[5] ** 2 for s, y in zip(plant.specs, ys))


@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 6.3), st.booleans())
@settings(max_examples=60, deadline=None)
def test_outline_distance_matches_shapely(px, py, theta, concave):
    spec = polygon(L_SHAPE, 1.0, 0.5) if concave else rectangle(0.4, 0.2, 1.0, 0.5)
    pose = (0.1, -0.2, theta)
    pts = np.array([[px, py], [0.1, -0.2]])
    d, n = outline_distance(spec, pose, pts)
    world = spec.world_polygon(pose)
    for k, p in enumerate(pts):
        ref = world.exterior.distance(shapely.Point(p))
        assert abs(abs(d[k]) - ref) < 1e-12
        assert (d[k] < 0) == world.contains(shapely.Point(p)) or ref < 1e-12
        assert abs(np.linalg.norm(n[k]) - 1) < 1e-12
        if ref > 1e-9:  # moving along the normal by the distance reaches the outline
            q = p - n[k] * d[k]
            assert world.exterior.distance(shapely.Point(q)) < 1e-9


def test_corner_to_corner_contact_pushes_along_the_faces():
    a, b = rectangle(0.3, 0.3, 1.0, 0.5), rectangle(0.3, 0.3, 1.0, 0.5)
    cs = pair_contacts(0, a, [0, 0, 0], 1, b, [0.3, 0, 0], 1e-3)
    assert len(cs) == 2  # edge on edge: the two ends of the shared edge
    for c in cs:
        assert abs(c.gap) < 1e-15
        np.testing.assert_allclose(np.abs(c.normal), [1, 0], atol=1e-15)
    cs = pair_contacts(0, a, [0, 0, 0], 1, b, [0.3005, 0.3, 0], 1e-3)  # corners 0.5 mm apart along x
    assert len(cs) >= 1
    for c in cs:
        assert abs(c.gap - 5e-4) < 1e-12
        np.testing.assert_allclose(np.abs(c.normal), [1, 0], atol=1e-15)
    assert pair_contacts(0, a, [0, 0, 0], 1, b, [0.302, 0.3, 0], 1e-3) == []


def free_plant(specs, mu=0.3, law="coulomb", dt=1e-3):
    """Parcels on an array whose wheels are stopped: under the paper's Coulomb law a stopped wheel gives no force
    (eq. 21, sign 0), so the parcels are free bodies in the plane except for each other."""
    cells = layout.grid(70, 70, 0.05)  # fine enough that no outline ever rests on a single line of cells
    return cells, Plant(cells, specs, LAWS[law], G, Integration(dt=dt), ContactParams(mu=mu))


def test_head_on_inelastic_impact_of_equal_boxes():
    specs = [rectangle(0.3, 0.3, 1.0, 0.5, name="a"), rectangle(0.3, 0.3, 1.0, 0.5, name="b")]
    cells, plant = free_plant(specs)
    ys = [np.array([0.6, 2.0, 0, 0.4, 0, 0]), np.array([1.5, 2.0, 0, 0, 0, 0])]
    active = [True, True]
    trs = plant.advance(ys, active, np.zeros((cells.n, 2)), 0.0, 3.0, 0.01)
    # Perfectly inelastic: both at v/2; contact when the 0.6 m gap has closed at 0.4 m/s (t = 1.5 s)
    np.testing.assert_allclose(ys[0][3:], [0.2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ys[1][3:], [0.2, 0, 0], atol=1e-12)
    np.testing.assert_allclose([ys[0][0], ys[1][0]], [0.6 + 0.6 + 0.3, 1.5 + 0.3], atol=1e-3)
    assert abs(ys[1][0] - ys[0][0] - 0.3) < 1e-9  # touching, not overlapping
    contact = [e for e in trs[0].events if e.kind == "contact"]
    assert len(contact) == 1 and contact[0].partner == "b" and abs(contact[0].t - 1.5) <= 1e-3 + 1e-9
    assert plant.record.parcel_contacts == 1 and plant.record.undetected_overlaps == 0


shapes = st.sampled_from(["square", "bar", "L"])


def make(kind, name, mass):
    if kind == "square":
        return rectangle(0.25, 0.25, mass, 0.5, name=name)
    if kind == "bar":
        return rectangle(0.45, 0.2, mass, 0.5, name=name)  # wide enough never to rest on one line of cells
    return polygon(L_SHAPE, mass, 0.5, name=name)


@given(shapes, shapes, st.floats(0.5, 3), st.floats(0.5, 3), st.floats(-0.15, 0.15), st.floats(0, 6.3),
       st.floats(0, 6.3), st.floats(0.1, 0.6), st.floats(-2, 2), st.floats(0, 1))
@settings(max_examples=15, deadline=None)
def test_free_collisions_conserve_momentum_and_never_gain_energy(ka, kb, ma, mb, offset, tha, thb, v, w, mu):
    specs = [make(ka, "a", ma), make(kb, "b", mb)]
    cells, plant = free_plant(specs, mu=mu)
    ys = [np.array([1.3, 2.0 + offset, tha, v, 0.0, w]), np.array([2.2, 2.0, thb, -v / 2, 0.0, 0.0])]
    if overlap_area(specs[0], ys[0], specs[1], ys[1]) > 0:
        return
    p0, L0 = momentum(plant, ys)
    e0 = kinetic(plant, ys)
    active = [True, True]
    plant.advance(ys, active, np.zeros((cells.n, 2)), 0.0, 1.2, 0.05)
    assert active == [True, True]
    p1, L1 = momentum(plant, ys)
    scale = sum(s.mass for s in specs) * (v + 2 * 0.3)
    np.testing.assert_allclose(p1, p0, atol=1e-9 * scale)
    assert abs(L1 - L0) < 1e-9 * scale * 3
    assert kinetic(plant, ys) <= e0 * (1 + 1e-9) + 1e-12
    assert plant.record.undetected_overlaps == 0
    assert plant.record.max_penetration_m < 5e-4  # stated tolerance: slop 0.1 mm plus rotation within a step
    assert overlap_area(specs[0], ys[0], specs[1], ys[1]) < 5e-4 * 0.5  # that depth along at most a side


@pytest.mark.parametrize("law", ["coulomb", "stick_slip"])
def test_opposed_fields_press_two_boxes_together(law):
    """Box a on wheels driving +x, box b on wheels driving -x, touching at the boundary. Every wheel slides
    (the parcels are far slower than the wheels), so each box feels mu m g toward the other: the pair accelerates
    toward the lighter one at a = mu g (ma - mb) / (ma + mb) and presses with 2 mu g ma mb / (ma + mb)."""
    mu, ma, mb, V = 0.5, 3.0, 1.0, 2.0
    cells = layout.grid(40, 5, 0.1)
    vel = np.where(cells.positions[:, :1] < 2.05, [V, 0.0], [-V, 0.0])  # cells sit at multiples of the pitch
    specs = [rectangle(0.3, 0.3, ma, mu, name="a"), rectangle(0.3, 0.3, mb, mu, name="b")]
    plant = Plant(cells, specs, LAWS[law], G, Integration(dt=1e-3), ContactParams(mu=0.0))
    ys = [np.array([1.9, 0.2, 0, 0, 0, 0]), np.array([2.2, 0.2, 0, 0, 0, 0])]
    T = 0.1  # short enough that no cell centre is crossed (the pair moves ~2.5 cm)
    trs = plant.advance(ys, [True, True], vel, 0.0, T, 0.01)
    a = mu * G * (ma - mb) / (ma + mb)
    for y in ys:
        assert abs(y[3] - a * T) < 1e-9
        assert abs(y[4]) < 1e-12 and abs(y[5]) < 1e-9
    assert abs(ys[1][0] - ys[0][0] - 0.3) < 1e-9
    assert abs(ys[0][0] - (1.9 + 0.5 * a * T * T)) < a * T * 1e-3 * 2  # semi-implicit Euler, O(dt)
    assert [e.kind for e in trs[0].events] == ["contact"]
    if law == "stick_slip":  # the energy account balances for each parcel, contact work included
        for tr in trs:
            s = tr.stats
            gained = s["kinetic_end"] - s["kinetic_start"]
            flows = s["wheel_work"] - s["friction_dissipation"] - s["step_dissipation"] + s["contact_work"]
            assert abs(gained - flows) < 1e-10
        assert trs[0].stats["contact_work"] + trs[1].stats["contact_work"] <= 1e-12


def scenario(parcels, field=None, duration=2.0, law="coulomb"):
    return parse_scenario({
        "name": "t", "duration": duration, "output_dt": 0.01,
        "array": {"kind": "grid", "nx": 40, "ny": 30, "pitch": 0.1},
        "field": field or {"kind": "uniform", "velocity": [0.2, 0.0]},
        "friction": {"law": law},
        "parcels": parcels,
    }).build()


def box(name, x, y, vx=0.0):
    return {"name": name, "length": 0.3, "width": 0.25, "mass": 1.0, "mu": 0.5, "x": x, "y": y, "vx": vx}


@pytest.mark.parametrize("y_b, duration, exact", [(2.7, 0.2, True), (0.5, 1.0, False)])
def test_parcels_that_never_meet_run_as_alone(y_b, duration, exact):
    """Far apart (the rigorous reach bound says no pair can meet before the end): bit for bit the single-parcel
    runs. 5 cm apart side by side on a uniform field: the plant cuts time into windows (restarting the integrator),
    within its tolerance."""
    both = run(scenario([box("a", 0.5, 0.2), box("b", 0.5, y_b)], duration=duration, law="viscous"))
    for k, name in enumerate(("a", "b")):
        alone = run(scenario([box(name, 0.5, (0.2, y_b)[k])], duration=duration, law="viscous"))
        mine, ref = both.parcels[k].trajectory, alone.parcels[0].trajectory
        np.testing.assert_array_equal(mine.times, ref.times)
        if exact:
            np.testing.assert_array_equal(mine.states, ref.states)
        else:
            np.testing.assert_allclose(mine.states, ref.states, rtol=0, atol=1e-8)
    assert both.stats["plant"]["parcel_contacts"] == 0
    assert (both.stats["plant"]["windows"] == 1) == exact


def test_parcels_of_one_weight_share_solved_supports():
    """A support pattern solved for one parcel is not solved again for another of the same weight (eqs. 13-19 do
    not involve the outline or the wheels); a parcel of another weight solves its own. Each still runs bit for bit
    as it would alone."""
    heavy = {**box("c", 3.3, 1.45), "mass": 2.0}
    parcels = [box("a", 0.5, 0.2), box("b", 0.5, 2.7), heavy]  # b rests on a's patterns, 25 cells away
    together = run(scenario(parcels, duration=0.2, law="viscous"))
    assert together.stats["plant"]["windows"] == 1  # too far apart to meet: one window, as alone
    solves = [p.trajectory.stats["solves"] for p in together.parcels]
    for k, spec in enumerate(parcels):
        alone = run(scenario([spec], duration=0.2, law="viscous")).parcels[0].trajectory
        np.testing.assert_array_equal(together.parcels[k].trajectory.states, alone.states)
        if spec["name"] == "b":
            assert alone.stats["solves"] > 0 and solves[k] == 0
        else:
            assert solves[k] == alone.stats["solves"] > 0


def test_a_fast_parcel_catches_up_and_pushes_a_slow_one():
    """Viscous law: a leader released at rest is pushed by a follower released fast; both end riding the field."""
    res = run(scenario([box("follower", 0.5, 0.3, vx=1.0), box("leader", 0.9, 0.3)], law="viscous", duration=1.5))
    s = res.summary()
    assert s["plant"]["parcel_contacts"] >= 1 and s["plant"]["undetected_overlaps"] == 0
    f, l = (p.trajectory for p in res.parcels)
    gaps = l.states[:, 0] - f.states[:, 0] - 0.3
    assert gaps.min() > -5e-4
    np.testing.assert_allclose([f.states[-1, 3], l.states[-1, 3]], 0.2, atol=1e-3)
    assert s["parcels"][0]["contacts_with_parcels"] >= 1


def test_contact_parameters_are_validated():
    from virtual_vehicle.errors import ScenarioError

    with pytest.raises(ScenarioError, match="slop"):
        parse_scenario({"duration": 1, "array": {"kind": "row", "n": 3, "pitch": 0.1},
                        "field": {"kind": "uniform", "velocity": [0.1, 0]}, "contacts": {"slop": 0.01, "margin": 0.001},
                        "parcels": [box("a", 0.1, 0.0)]})
