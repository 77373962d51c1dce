"""Stick-slip parcels riding their wheels rigidly (issue 32 items 1 and 6): the closed-form step the plant takes for
them together equals the event-driven mode integration over long runs, and a parcel that stops riding (its field
changes, a wheel fails, its support changes, another parcel pushes it) goes back to the exact path in time."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from virtual_vehicle.engine.plant import Integration, Plant
from virtual_vehicle.engine.ride import rigid_motion
from virtual_vehicle.model import layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.physics.stick_modes import zonotope_inradius

CELLS = layout.grid(30, 14, 0.1)
SPEC = parcel.rectangle(0.33, 0.24, 1.5, 0.6, mu_static=0.8)
PERIOD = 0.01
TOL = 1e-9  # m, rad (and m/s, rad/s)


def aisle(vx: float, vy: float) -> np.ndarray:
    """A constant field: every wheel's surface velocity (vx, vy), m/s."""
    return np.tile([vx, vy], (CELLS.n, 1)).astype(float)


def turn(omega: float, centre) -> np.ndarray:
    """The wheels of a rigid rotation at ``omega`` (rad/s) about ``centre`` (m)."""
    p = CELLS.positions - np.asarray(centre, dtype=float)
    return np.column_stack([-omega * p[:, 1], omega * p[:, 0]])


def run(fields, y0s, batch: bool, specs=None):
    """Parcels from states ``y0s`` ticked at 100 Hz, tick k under ``fields(k)`` (m/s): each tick's trajectories
    (None for an inactive parcel), the plant's record."""
    specs = specs or [SPEC] * len(y0s)
    plant = Plant(CELLS, specs, laws.StickSlipLaw(), integration=Integration(batch=batch))
    ys, active = [np.array(y, dtype=float) for y in y0s], [True] * len(y0s)
    ticks = []
    k = 0
    while (V := fields(k)) is not None:
        ticks.append(plant.advance(ys, active, V, k * PERIOD, (k + 1) * PERIOD, PERIOD))
        k += 1
    return ticks, plant.record


def assert_same(a, b):
    """Two runs' ticks agree: the same parcels active, states within TOL, and each parcel's events the same, at
    times within TOL (an event at a tick's very end may fall at the start of the next tick in the other run)."""
    assert len(a) == len(b)
    for ta, tb in zip(a, b):
        for ra, rb in zip(ta, tb):
            assert (ra is None) == (rb is None)
            if ra is None:
                continue
            assert ra.status == rb.status
            np.testing.assert_allclose(ra.times, rb.times, rtol=0, atol=1e-12)
            np.testing.assert_allclose(ra.states, rb.states, rtol=0, atol=TOL)
    for i in range(len(a[0])):
        ea = [e for t in a if t[i] is not None for e in t[i].events]
        eb = [e for t in b if t[i] is not None for e in t[i].events]
        assert [(e.kind, e.entered, e.left, e.lifted, e.touched) for e in ea] == \
            [(e.kind, e.entered, e.left, e.lifted, e.touched) for e in eb]
        np.testing.assert_allclose([e.t for e in ea], [e.t for e in eb], rtol=0, atol=TOL)


def test_rigid_motion_is_the_integrated_twist():
    """The closed form is the rigid twist integrated (a rotation about its centre, and the translation at omega 0)."""
    rng = np.random.default_rng(3)
    times = np.linspace(0.0, 0.02, 5) + 1.5
    Y = np.column_stack([rng.uniform(0, 3, (6, 3)), rng.normal(0, 0.5, (6, 3))])
    Y[0, 5], Y[1, 5] = 0.0, 1e-9
    got = rigid_motion(Y, times, 1.5)

    def rhs(t, y):
        return [y[3], y[4], y[5], -y[5] * y[4], y[5] * y[3], 0.0]

    for k, y in enumerate(Y):
        want = solve_ivp(rhs, (1.5, times[-1]), y, t_eval=times, rtol=1e-13, atol=1e-15).y.T
        np.testing.assert_allclose(got[k], want, rtol=0, atol=1e-12)
    assert got[:, 0].tolist() == Y.tolist()


def test_zonotope_inradius():
    """Three independent generators make a parallelepiped, whose inradius is its least face distance
    ``|det G| / |G_p x G_q|``; more generators only widen it; below rank 3 it holds no ball."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        G = rng.normal(size=(3, 3))
        det = abs(np.linalg.det(G))
        want = min(det / np.linalg.norm(np.cross(G[p], G[q])) for p, q in ((0, 1), (0, 2), (1, 2)))
        assert zonotope_inradius(G) == pytest.approx(want, rel=1e-12)
        more = np.vstack([G, rng.normal(size=(4, 3))])
        assert zonotope_inradius(more) >= want
        u = rng.normal(size=(2000, 3))
        u /= np.linalg.norm(u, axis=1)[:, None]
        assert zonotope_inradius(more) <= np.abs(u @ more.T).sum(axis=1).min() + 1e-12  # h(u) over directions
    flat = rng.normal(size=(6, 3))
    flat[:, 2] = 0.0
    assert zonotope_inradius(flat) <= 1e-12


@settings(max_examples=8, deadline=None)
@given(kind=st.sampled_from(["aisle", "turn"]), speed=st.floats(0.1, 0.5), angle=st.floats(-np.pi, np.pi),
       x=st.floats(0.6, 2.2), y=st.floats(0.5, 0.9), theta=st.floats(-np.pi, np.pi), start=st.floats(0.0, 1.0))
@example(kind="aisle", speed=0.5, angle=0.0, x=1.0, y=0.5, theta=0.0, start=1.0)  # a cell leaves at a tick's end
@example(kind="aisle", speed=0.5, angle=0.0, x=1.0, y=0.625, theta=0.0, start=0.0)  # an edge 5 mm beside a row
def test_the_ride_is_the_mode_integration(kind, speed, angle, x, y, theta, start):
    """Over 60 ticks a parcel picked up from rest (or from part of the field's speed) by a constant aisle field or a
    rigid rotation moves as the event-driven engine moves it, to 1e-9 m / rad, and its windows ride (most of them
    on an aisle)."""
    if kind == "aisle":
        V = aisle(speed * np.cos(angle), speed * np.sin(angle))
        v, omega = V[0], 0.0
    else:
        omega = speed / 0.6 * (1.0 if angle >= 0 else -1.0)
        centre = np.array([x + 0.6 * np.cos(angle), y + 0.6 * np.sin(angle)])
        V = turn(omega, centre)
        v = omega * np.array([centre[1] - y, x - centre[0]])  # omega x (X - centre)
    y0 = [x, y, theta, *(start * v), start * omega]
    ticks = 60 if kind == "aisle" else 40
    a, rec_a = run(lambda k: V if k < ticks else None, [y0], True)
    b, rec_b = run(lambda k: V if k < ticks else None, [y0], False)
    assert_same(a, b)
    assert rec_b.quiet_steps == 0
    riding = sum(1 for t in a if t[0] is not None and t[0].status == "completed")
    # A translation rides most windows; a fast rigid turn over 0.1 m cells meets a support change in most windows
    # (at 0.5 m/s picked up from rest, 3 of 40 rode), so there the ride only has to be taken at all.
    assert rec_a.quiet_steps > (0.3 * riding if kind == "aisle" else 0)


def test_a_field_change_ends_the_ride_at_the_tick():
    """The field slows at tick 30: that tick is integrated exactly (the parcel slips, then sticks again), and the
    run is the exact one throughout."""
    fields = lambda k: None if k >= 60 else aisle(0.4, 0.0) if k < 30 else aisle(0.1, 0.05)  # noqa: E731
    a, rec = run(fields, [[0.6, 0.7, 0.2, 0.0, 0.0, 0.0]], True)
    b, _ = run(fields, [[0.6, 0.7, 0.2, 0.0, 0.0, 0.0]], False)
    assert_same(a, b)
    # a ride (no events: the ride stepper's), then the exact path from the change on (the event engine, or its
    # closed form for a translation over a uniform field, engine.glide: with the mode events the ride cannot have)
    assert a[29][0].rhs_evals == 0 and not a[29][0].events and a[30][0].events
    assert any(e.kind == "stick" for e in a[30][0].events)  # where the parcel has slowed to its wheels
    assert rec.quiet_steps > 20


def test_a_wheel_fault_ends_the_ride():
    """A stuck row of wheels under the riding parcel (tick 25 on): the field is no longer a rigid twist there."""
    def fields(k):
        if k >= 50:
            return None
        V = aisle(0.3, 0.0)
        if k >= 25:
            V[np.abs(CELLS.positions[:, 1] - 0.7) < 0.02] = 0.0
        return V

    a, rec = run(fields, [[0.6, 0.7, 0.0, 0.3, 0.0, 0.0]], True)
    b, _ = run(fields, [[0.6, 0.7, 0.0, 0.3, 0.0, 0.0]], False)
    assert_same(a, b)
    assert a[24][0].rhs_evals == 0 < a[25][0].rhs_evals
    assert rec.quiet_steps >= 10


def test_a_support_change_ends_the_ride():
    """A parcel riding off the array's end: its support shrinks until it tips off, as in the exact run."""
    fields = lambda k: None if k >= 80 else aisle(0.4, 0.0)  # noqa: E731
    a, rec = run(fields, [[2.6, 0.7, 0.0, 0.4, 0.0, 0.0]], True)
    b, _ = run(fields, [[2.6, 0.7, 0.0, 0.4, 0.0, 0.0]], False)
    assert_same(a, b)
    assert any(t[0] is not None and t[0].status == "tipped" for t in a)
    assert rec.quiet_steps >= 5


def test_a_push_ends_the_ride():
    """A parcel thrown faster than its wheels catches up with one riding them ahead of it: they push each other and
    are stepped together, then ride again; the run is the exact one."""
    fields = lambda k: None if k >= 60 else aisle(0.2, 0.0)  # noqa: E731
    y0s = [[1.0, 0.7, 0.0, 1.2, 0.0, 0.0], [1.38, 0.7, 0.0, 0.2, 0.0, 0.0]]
    a, rec = run(fields, y0s, True)
    b, rec_b = run(fields, y0s, False)
    assert rec.parcel_contacts > 0 and rec.parcel_contacts == rec_b.parcel_contacts
    assert rec.grouped_steps == rec_b.grouped_steps > 0
    assert_same(a, b)
    assert rec.quiet_steps > 0  # the parcel ahead rode until it was pushed (then the two stay in reach, grouped)


def test_a_ride_window_closes_the_energy_account():
    """A ride window does no wheel work, dissipates nothing and keeps the kinetic energy, and a run of them joined
    to exact windows keeps the account: wheel work = kinetic energy gained + dissipation, each dissipation >= 0."""
    fields = lambda k: None if k >= 40 else aisle(0.35, 0.1)  # noqa: E731
    plant = Plant(CELLS, [SPEC], laws.StickSlipLaw())
    ys, active = [np.array([0.6, 0.6, 0.4, 0.0, 0.0, 0.0])], [True]
    work = gained = lost = 0.0
    rides = 0
    for k in range(40):
        quiet = plant.record.quiet_steps
        tr = plant.advance(ys, active, fields(k), k * PERIOD, (k + 1) * PERIOD, PERIOD)[0]
        s = tr.stats
        if plant.record.quiet_steps > quiet:  # a closed-form ride (the ride stepper counts its windows there)
            rides += 1
            assert s["wheel_work"] == 0.0 and s["friction_dissipation"] == 0.0
            assert s["kinetic_end"] == pytest.approx(s["kinetic_start"], rel=1e-12)
        assert s["friction_dissipation"] >= 0.0
        work += s["wheel_work"]
        gained += s["kinetic_end"] - s["kinetic_start"]
        lost += s["friction_dissipation"] + s["step_dissipation"]
    assert rides > 20
    assert work == pytest.approx(gained + lost, rel=1e-6)


def test_measured_again_in_one_call_as_anew():
    """Parcels riding on their last anchor's cells are measured again in one compiled call; the same run taken back
    to its own state at each tick (every anchor forgotten, the kept proofs measured again in Python at their anchors,
    as a resumed run's are) is the same run to the last bit: the same windows ride, the same states. Across a field
    change and support changes, three parcels."""
    fields = lambda k: None if k >= 45 else aisle(0.4, 0.05) if k < 25 else turn(0.3, (1.5, 0.7))  # noqa: E731
    y0s = [[0.5, 0.4, 0.1, 0.0, 0.0, 0.0], [1.2, 1.0, 0.0, 0.4, 0.05, 0.0], [2.0, 0.6, -0.3, 0.0, 0.0, 0.0]]
    runs = []
    for forget in (False, True):
        plant = Plant(CELLS, [SPEC] * 3, laws.StickSlipLaw())
        ys, active = [np.array(y, dtype=float) for y in y0s], [True] * 3
        ticks = []
        for k in range(45):
            if forget:
                plant.restore(plant.state())  # (the plant's steppers forget their anchors, take the proofs up)
            ticks.append(plant.advance(ys, active, fields(k), k * PERIOD, (k + 1) * PERIOD, PERIOD))
        runs.append((ticks, plant.record.quiet_steps))
    (a, rides_a), (b, rides_b) = runs
    assert rides_a == rides_b > 60
    for ta, tb in zip(a, b):
        for ra, rb in zip(ta, tb):
            assert np.array_equal(ra.times, rb.times) and np.array_equal(ra.states, rb.states)
            drop = ("pieces_cached",)  # (the forgetting run's models are made again each tick: fewer cached)
            assert {k: v for k, v in ra.stats.items() if k not in drop} == \
                {k: v for k, v in rb.stats.items() if k not in drop}


def test_a_track_takes_rides_as_their_trajectories():
    """A networked run's track takes ride windows in from the stepper's block, their stats joined only when read:
    the same samples, counts and stats (values and types) as a track that takes in each window's trajectory, over
    rides, exact windows and rides again."""
    from virtual_vehicle.run.sim import ParcelTrack

    fields = lambda k: aisle(0.4, 0.0) if k < 20 or k >= 24 else aisle(0.1, 0.05)  # noqa: E731
    plant = Plant(CELLS, [SPEC, SPEC], laws.StickSlipLaw())
    ys, active = [np.array([0.6, 0.7, 0.2, 0.0, 0.0, 0.0]), np.array([1.5, 0.4, 0.0, 0.4, 0.0, 0.0])], [True, True]
    blocks, whole = [ParcelTrack(), ParcelTrack()], [ParcelTrack(), ParcelTrack()]
    rides = 0
    for k in range(45):
        grid = np.array([k * PERIOD]) if k % 5 == 0 else np.zeros(0)
        out, quiet = plant.advance_blocks(ys, active, fields(k), k * PERIOD, (k + 1) * PERIOD, PERIOD,
                                          sample_times=grid)
        for i, tr in enumerate(out):
            if tr is not None:
                blocks[i].add(tr, grid)
                whole[i].add(tr, grid)
        for i, steps, j in quiet:
            rides += steps.summed
            blocks[i].add_quiet(steps, j, grid)
            whole[i].add(steps.trajectory(j), grid)
        if k in (10, 30):  # read mid-run, as a checkpoint does
            assert [t.to_data()["stats_pieces"][0]["stats"] for t in blocks] == \
                [t.to_data()["stats_pieces"][0]["stats"] for t in whole]
    assert rides > 40
    for x, y in zip(blocks, whole):
        tx, ty = x.trajectory(), y.trajectory()
        assert np.array_equal(tx.times, ty.times) and np.array_equal(tx.states, ty.states)
        assert (tx.segments, tx.rhs_evals, tx.status, tx.t_end) == (ty.segments, ty.rhs_evals, ty.status, ty.t_end)
        assert tx.stats == ty.stats
        assert [type(v) for v in tx.stats.values()] == [type(v) for v in ty.stats.values()]


def test_a_parcel_slipping_on_a_wheel_under_it_is_not_measured():
    """A parcel at rest on moving wheels slips on the cell under its centre: it cannot ride, so the ride stepper
    makes it no anchor (its window goes to the exact path); a parcel at its wheels' speed is measured and rides."""
    V = aisle(0.3, 0.0)
    plant = Plant(CELLS, [SPEC, SPEC], laws.StickSlipLaw())
    ys = [np.array([0.6, 0.7, 0.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.7, 0.0, 0.3, 0.0, 0.0])]
    (slipping, riding), quiet = plant.advance_blocks(ys, [True, True], V, 0.0, PERIOD, PERIOD)
    assert 0 not in plant._ride.anchors and 1 in plant._ride.anchors
    assert slipping is not None and riding is None and [q.parcel for q in quiet] == [1]


def test_a_parcel_moving_onto_other_cells_is_not_measured():
    """A parcel at its wheels' speed whose front edge reaches a cell within the window has a support event on the
    way: it cannot ride, so the ride stepper makes it no anchor (the closed form writes its window, the event in
    it); a parcel whose cells stay under it is measured and rides."""
    V = aisle(0.3, 0.0)
    plant = Plant(CELLS, [SPEC, SPEC], laws.StickSlipLaw())
    front = 1.1 - 0.001 - SPEC.half_extents[0]  # its front edge 1 mm short of the cells at x = 1.1 m (3 mm a tick)
    ys = [np.array([front, 0.7, 0.0, 0.3, 0.0, 0.0]), np.array([2.0, 0.7, 0.0, 0.3, 0.0, 0.0])]
    measured, measure = [], plant._ride.measure
    plant._ride.measure = lambda i, *args: measured.append(i) or measure(i, *args)
    (crossing, riding), quiet = plant.advance_blocks(ys, [True, True], V, 0.0, PERIOD, PERIOD)
    assert measured == [1] and 1 in plant._ride.anchors
    assert riding is None and [q.parcel for q in quiet] == [1]
    assert [e.kind for e in crossing.events] == ["support"]
    assert crossing.events[0].entered == (6 * 30 + 11, 7 * 30 + 11, 8 * 30 + 11)  # x = 1.1, y = 0.6-0.8 m
    np.testing.assert_allclose(crossing.events[0].t, 0.001 / 0.3, rtol=0, atol=1e-12)
