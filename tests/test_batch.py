"""Quiet windows stepped together (issue 8, performance): the batched step is the event engine's to the last bit
(and scipy's DOP853 step: test_kernel), a window the stepper calls quiet has no event in the event-driven engine
either, and runs with and without batching agree."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.engine.batch import QuietStepper
from virtual_vehicle.engine.dynamics import Event, ParcelModel, Trajectory, integrate
from virtual_vehicle.engine.plant import Integration, Plant
from virtual_vehicle.model import layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.physics.collide import point_reach, reach_bounds, wheel_speed_of
from virtual_vehicle.run.sim import run, run_network

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_scale import scenario as scale_scenario  # noqa: E402

CELLS = layout.grid(12, 12, 0.1)
SPEC = parcel.rectangle(0.33, 0.24, 1.5, 0.8)
LAWS = {"viscous": laws.ViscousLaw(), "coulomb": laws.CoulombLaw()}


def _field(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.3, 0.3, (CELLS.n, 2))


def _pieces(law, seed, n=20):
    """n parcels' states under a random field, placed at random inside the array, and their model."""
    rng = np.random.default_rng(seed)
    model = ParcelModel(CELLS, SPEC, _field(seed), law)
    ys = [np.array([*rng.uniform(0.35, 0.75, 2), rng.uniform(-np.pi, np.pi), *rng.normal(0, 0.1, 2),
                    rng.normal(0, 0.5)]) for _ in range(n)]
    return model, np.array(ys)


def test_reach_bounds_are_point_reach_for_many_parcels():
    rng = np.random.default_rng(0)
    for law in ("viscous", "coulomb"):
        ys = [np.array([0, 0, 0, *rng.normal(0, 0.3, 3)]) for _ in range(6)]
        mu = rng.uniform(0, 2, 6)
        want = np.array([point_reach(SPEC, y, 0.02, law=law, mu_max=m, gravity=9.81, wheel_speed=0.4)
                         for y, m in zip(ys, mu)])
        R = SPEC.radius
        s0 = np.array([np.hypot(y[3], y[4]) + abs(y[5]) * R for y in ys])
        lever = 1 + SPEC.mass * R * R / SPEC.inertia
        got = reach_bounds(s0, mu * lever, 0.02, law=law, gravity=9.81, wheel_speed=0.4, lever=np.full(6, lever))
        np.testing.assert_allclose(np.column_stack(got), want, rtol=1e-14)



@pytest.mark.parametrize("law", ["viscous", "coulomb", "stick_slip"])
def test_point_reaches_are_point_reach_to_the_last_bit(law):
    """The planner's bounds for every parcel at once are the scalar bounds, the same numbers (its windows, and so
    the runs, must not change with how many parcels are planned together): several outlines, speed floors, and
    parcels whose wheels give them nothing (mu = 0, the slow branch of the viscous bound)."""
    from virtual_vehicle.physics.collide import lever_of, point_reaches

    rng = np.random.default_rng(1)
    specs = [SPEC, parcel.rectangle(0.5, 0.2, 3.0, 0.4), parcel.polygon([[0, 0], [0.3, 0], [0.1, 0.25]], 1.5, 0.8)]
    specs = [specs[k] for k in rng.integers(0, 3, 40)]
    Y = np.column_stack([rng.uniform(0, 1, (40, 3)), rng.normal(0, 0.3, (40, 3))])
    mu = np.where(rng.random(40) < 0.2, 0.0, rng.uniform(0, 2, 40))
    floor = np.where(rng.random(40) < 0.5, 0.0, rng.uniform(0, 1, 40))
    for window in (0.01, 1e-15):
        want = [point_reach(s, y, window, law=law, mu_max=m, gravity=9.81, wheel_speed=0.4, speed_floor=f)
                for s, y, m, f in zip(specs, Y, mu, floor)]
        got = point_reaches(np.array([s.radius for s in specs]), np.array([lever_of(s) for s in specs]), Y, window,
                            law=law, mu_max=mu, gravity=9.81, wheel_speed=0.4, speed_floor=floor)
        assert np.column_stack(got).tolist() == [list(w) for w in want]


@settings(max_examples=60, deadline=None)
@given(x=st.floats(0.3, 0.8), y=st.floats(0.3, 0.8), th=st.floats(-np.pi, np.pi), vx=st.floats(-0.4, 0.4),
       vy=st.floats(-0.4, 0.4), om=st.floats(-2, 2), seed=st.integers(0, 50), window=st.sampled_from([0.002, 0.01]),
       law=st.sampled_from(["viscous", "coulomb"]))
def test_a_window_called_quiet_has_no_event(x, y, th, vx, vy, om, seed, window, law):
    """Soundness: whenever the stepper proves a window quiet and steps it, the event-driven engine over the same
    window finds no support change and ends where the stepper ended."""
    model = ParcelModel(CELLS, SPEC, _field(seed), LAWS[law])
    _quiet_matches_engine(model, law, np.array([x, y, th, vx, vy, om]), window)


def _quiet_matches_engine(model, law, y0, window):
    stepper = QuietStepper(CELLS, [model.spec], LAWS[law], [model.spec.mu], 9.81, 1e-10, 1e-12)
    done, rest = stepper.step([model], [model], [0], [y0], model.velocities, 0.0, window, np.array([0.0, window]))
    ref = integrate(model, y0, 0.0, window, sample_times=np.array([0.0, window]))
    if 0 in stepper.anchors:  # measured where the parcel is: its supports are the engine's
        np.testing.assert_array_equal(stepper.anchors[0].support, model.support_at(y0))
    if done:
        assert done.idx == [0] and ref.events == [] and ref.status == "completed"
        assert done.trajectory(0).states.tolist() == ref.states.tolist()  # the engine's own step, to the last bit
    else:
        assert rest == [0]
    return bool(done)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(0.3, 0.8), y=st.floats(0.3, 0.8), th=st.floats(-np.pi, np.pi), speed=st.floats(0, 0.5),
       heading=st.floats(-np.pi, np.pi), om=st.floats(-0.5, 0.5), window=st.sampled_from([0.005, 0.01, 0.02]),
       law=st.sampled_from(["viscous", "coulomb"]))
def test_tight_bounds_riding_or_coasting_parcels_stay_sound(x, y, th, speed, heading, om, window, law):
    """Where the piece's bound is much tighter than the law's: a viscous parcel riding wheels that move with it
    (little slip) and a Coulomb parcel coasting over stopped wheels (no force at all)."""
    v = speed * np.array([np.cos(heading), np.sin(heading)])
    field = np.tile(v, (CELLS.n, 1)) if law == "viscous" else np.zeros((CELLS.n, 2))
    model = ParcelModel(CELLS, SPEC, field, LAWS[law])
    _quiet_matches_engine(model, law, np.array([x, y, th, *v, om]), window)


def _grazing(law, dx, dy, th, speed, heading, om, riding):
    """A parcel whose -x and -y edges lie ``dx``, ``dy`` (m) beyond a column and a row of cell centres, moving at
    ``speed`` (m/s) toward ``heading``; wheels moving with it (``riding``) or a random field."""
    v = speed * np.array([np.cos(heading), np.sin(heading)])
    if riding:
        field = np.tile(v, (CELLS.n, 1)) if law == "viscous" else np.zeros((CELLS.n, 2))
    else:
        field = _field(7)
    hl, hw = SPEC.half_extents
    return ParcelModel(CELLS, SPEC, field, LAWS[law]), np.array([0.4 + hl + dx, 0.4 + hw + dy, th, *v, om])


def _edge_decided(model, law, y0, window) -> bool:
    """Whether the stepper calls this window quiet although one clearance radius could not prove it."""
    stepper = QuietStepper(CELLS, [model.spec], LAWS[law], [model.spec.mu], 9.81, 1e-10, 1e-12)
    quiet = _quiet_matches_engine(model, law, y0, window)
    a = stepper.measure(0, [model], y0)
    wheel_speed = float(np.max(np.hypot(model.velocities[:, 0], model.velocities[:, 1])))
    r, _ = stepper.reach([0], y0[None], window, model.velocities, wheel_speed)
    return quiet and a.clear <= r[0]


@settings(max_examples=80, deadline=None)
@given(dx=st.floats(-0.006, 0.006), dy=st.floats(-0.006, 0.006), th=st.floats(-0.03, 0.03),
       speed=st.floats(0, 0.5), heading=st.floats(-np.pi, np.pi), om=st.floats(-0.3, 0.3),
       window=st.sampled_from([0.005, 0.01]), law=st.sampled_from(["viscous", "coulomb"]), riding=st.booleans())
def test_parcels_grazing_cells_edge_by_edge_stay_sound(dx, dy, th, speed, heading, om, window, law, riding):
    """The edge-by-edge check: edges within millimetres of rows of cell centres, moving any way."""
    model, y0 = _grazing(law, dx, dy, th, speed, heading, om, riding)
    _quiet_matches_engine(model, law, y0, window)


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_edges_moving_away_from_cells_are_quiet_and_toward_them_are_not(law):
    """A parcel whose trailing edge has just left a column of cell centres (1 mm behind it) runs on quietly though
    one radius of clearance could not prove it; driven the other way, into that column, it is never called quiet."""
    away, y_away = _grazing(law, 0.001, 0.05, 0.0, 0.3, 0.0, 0.0, riding=True)
    assert _edge_decided(away, law, y_away, 0.01)
    toward, y_toward = _grazing(law, 0.001, 0.05, 0.0, 0.3, np.pi, 0.0, riding=True)
    assert not _quiet_matches_engine(toward, law, y_toward, 0.01)
    rng = np.random.default_rng(5)
    decided = []
    for _ in range(60):
        model, y0 = _grazing(law, *rng.uniform(-0.004, 0.004, 2), rng.uniform(-0.01, 0.01), rng.uniform(0, 0.4),
                             rng.uniform(-np.pi, np.pi), rng.normal(0, 0.1), bool(rng.integers(2)))
        decided.append(_edge_decided(model, law, y0, 0.01))
    assert sum(decided) >= 4  # of 60 grazing windows, each checked against the engine (measured: 7 viscous, 5 coulomb)


PENTAGON = parcel.polygon([[0.0, 0.0], [0.3, 0.0], [0.36, 0.16], [0.15, 0.27], [-0.04, 0.14]], 1.2, 0.7)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(0.3, 0.8), y=st.floats(0.3, 0.8), th=st.floats(-np.pi, np.pi), speed=st.floats(0, 0.5),
       heading=st.floats(-np.pi, np.pi), om=st.floats(-1, 1), seed=st.integers(0, 50),
       window=st.sampled_from([0.005, 0.01]), law=st.sampled_from(["viscous", "coulomb"]))
def test_a_convex_polygon_is_checked_edge_by_edge_soundly(x, y, th, speed, heading, om, seed, window, law):
    """Five edges of different lengths and directions, the centre of mass off every symmetry: the edge-by-edge check
    uses the outline's own half-planes."""
    v = speed * np.array([np.cos(heading), np.sin(heading)])
    model = ParcelModel(CELLS, PENTAGON, _field(seed), LAWS[law])
    _quiet_matches_engine(model, law, np.array([x, y, th, *v, om]), window)


def test_a_convex_polygon_runs_past_cells_edge_by_edge():
    rng = np.random.default_rng(11)
    decided = 0
    for _ in range(80):
        v = rng.uniform(0.1, 0.4) * np.array([1.0, 0.0])
        model = ParcelModel(CELLS, PENTAGON, np.tile(v, (CELLS.n, 1)), LAWS["viscous"])
        decided += _edge_decided(model, "viscous", np.array([*rng.uniform(0.35, 0.75, 2), rng.uniform(-np.pi, np.pi),
                                                            *v, 0.0]), 0.01)
    assert decided >= 10  # of 80 windows, each checked against the engine (measured: 23)


def test_the_edges_of_many_parcels_at_once_are_each_parcels_own():
    """The edge-by-edge check of many parcels in one compiled call decides each as its own stepper does for it
    alone: parcels of two outlines (four and five edges) through the stepper's columns, each anchored twice (the
    columns written over), with different numbers of cells near them and under them (padded rows)."""
    rng = np.random.default_rng(3)
    specs = [SPEC, PENTAGON] * 15
    stepper = QuietStepper(CELLS, specs, LAWS["viscous"], [s.mu for s in specs], 9.81, 1e-10, 1e-12)
    anchors, models, Y = [], [], []
    for i, spec in enumerate(specs):
        v = rng.uniform(0.0, 0.4) * np.array([np.cos(h := rng.uniform(-np.pi, np.pi)), np.sin(h)])
        model = ParcelModel(CELLS, spec, np.tile(v, (CELLS.n, 1)), LAWS["viscous"])
        y = np.array([*rng.uniform(0.35, 0.75, 2), rng.uniform(-np.pi, np.pi), *v, rng.normal(0, 0.2)])
        first = np.array([*rng.uniform(0.35, 0.75, 2), rng.uniform(-np.pi, np.pi), *v, 0.0])
        anchors.append(stepper.measure(i, [model] * len(specs), first))  # measured elsewhere first: written over
        anchors.append(stepper.measure(i, [model] * len(specs), y))
        models.append(model)
        Y.append(y)
    anchors, Y, window = anchors[1::2], np.array(Y), 0.01
    columns = stepper.columns
    for k, a in enumerate(anchors):  # the rows written over hold the latest anchor's cells, padded with the sentinel
        count = columns.near_count[k]
        assert count == len(a.near) and columns.near[k, :count].tolist() == a.near.tolist()
        assert set(columns.near[k, count:].tolist()) <= {CELLS.n}
        assert columns.support[k, :len(a.support)].tolist() == a.support.tolist()
        assert set(columns.support[k, len(a.support):].tolist()) <= {CELLS.n}
    assert len({len(a.near) for a in anchors}) > 1 and len({len(a.support) for a in anchors}) > 1
    r, accel = rng.uniform(0.0, 0.004, len(specs)), rng.uniform(0.0, 0.001, len(specs))
    together = stepper.edges_clear(np.arange(len(specs)), Y, window, r, accel, stepper.radius, stepper.lever)
    alone = []
    for k, (spec, model, y) in enumerate(zip(specs, models, Y)):
        own = QuietStepper(CELLS, [spec], LAWS["viscous"], [spec.mu], 9.81, 1e-10, 1e-12)
        a = own.measure(0, [model], y)
        assert a.near.tolist() == anchors[k].near.tolist()  # the same anchor, no padding
        alone.append(bool(own.edges_clear(np.zeros(1, dtype=np.int64), y[None], window, r[k:k + 1],
                                          accel[k:k + 1], own.radius, own.lever)[0]))
    assert together.tolist() == alone and 0 < sum(alone) < len(alone)
    assert stepper.edges_clear(np.arange(len(specs))[::-1], Y[::-1], window, r[::-1], accel[::-1],
                               stepper.radius[::-1], stepper.lever[::-1]).tolist() == alone[::-1]


def test_a_parcel_at_rest_between_cell_centres_is_quiet():
    model = ParcelModel(CELLS, SPEC, _field(1), LAWS["viscous"])
    stepper = QuietStepper(CELLS, [SPEC], LAWS["viscous"], [SPEC.mu], 9.81, 1e-10, 1e-12)
    y0 = np.array([0.55, 0.55, 0.0, 0.0, 0.0, 0.0])
    done, rest = stepper.step([model], [model], [0], [y0], model.velocities, 0.0, 0.01, np.array([0.0, 0.005, 0.01]))
    tr = done.trajectory(0)
    assert rest == [] and done.idx == [0] and tr.times.tolist() == [0.0, 0.005, 0.01]
    ref = integrate(model, y0, 0.0, 0.01, sample_times=np.array([0.0, 0.005, 0.01]))
    assert tr.states.tolist() == ref.states.tolist() and done.last().tolist() == [ref.states[-1].tolist()]


def _compare(d: dict):
    out = {}
    for batch in (False, True):
        d = {**d, "integrator": {"batch": batch}}
        out[batch] = run_network(parse_scenario(d).build())
    off, on = out[False], out[True]
    assert off.stats["plant"]["quiet_steps"] == 0
    for a, b in zip(off.parcels, on.parcels):  # the same run to the last bit: quiet steps are the engine's own
        assert a.trajectory.status == b.trajectory.status
        np.testing.assert_array_equal(a.trajectory.times, b.trajectory.times)
        np.testing.assert_array_equal(a.trajectory.states, b.trajectory.states)
        assert [(e.kind, e.entered, e.left, e.lifted, e.touched) for e in a.trajectory.events] == \
            [(e.kind, e.entered, e.left, e.lifted, e.touched) for e in b.trajectory.events]
        assert [e.t for e in a.trajectory.events] == [e.t for e in b.trajectory.events]
    return on


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_networked_runs_agree_with_and_without_batching(law):
    d = scale_scenario(30, 25, 0.6)
    d["friction"] = {"law": law}
    on = _compare(d)
    assert on.stats["plant"]["quiet_steps"] > 100
    assert sum(len(p.trajectory.events) for p in on.parcels) > 0  # events happened and were found by the engine


def test_networked_trajectories_hold_the_output_grid_and_the_end():
    """A networked run keeps of each parcel the samples on the output grid (every ``output_dt`` s) while it is on the
    array and its last state: not the 100 Hz control ticks, nor the plant's restarts within a tick (the plant hands
    its tracks the untrimmed trajectory of each tick)."""
    res = run_network(parse_scenario(scale_scenario(30, 5, 0.32)).build())  # output_dt 0.05 s
    grid = np.round(np.arange(0.0, 0.32, 0.05), 12)
    for p in res.parcels:
        times = p.trajectory.times
        on = np.isin(np.round(times, 12), grid)
        assert on[:-1].all() and times[-1] == pytest.approx(0.32)
        assert times[on].tolist() == pytest.approx(grid[grid >= times[0] - 1e-12].tolist())


def test_a_hall_with_belts_agrees_with_and_without_batching():
    """hybrid_junction: plain feed belts (a contact layer of belts) into a sorting floor. Run under the viscous law
    (2 s/m, as it was bundled before it moved to stick-slip): quiet steps batch the laws without stick/slip modes."""
    out = {}
    for batch in (False, True):
        sc, _ = load_scenario("hybrid_junction")
        sc = sc.model_copy(update={"duration": 10.0, "integrator": sc.integrator.model_copy(update={"batch": batch}),
                                   "friction": sc.friction.model_copy(update={"law": "viscous"}),
                                   "parcels": [p.model_copy(update={"mu": 2.0, "mu_static": None})
                                               for p in sc.parcels]})
        out[batch] = run(sc.build())
    assert out[True].stats["plant"]["quiet_steps"] > 1000
    for a, b in zip(out[False].parcels, out[True].parcels):
        np.testing.assert_array_equal(a.trajectory.states, b.trajectory.states)
        assert [(e.kind, e.entered, e.left, e.lifted, e.touched) for e in a.trajectory.events] == \
            [(e.kind, e.entered, e.left, e.lifted, e.touched) for e in b.trajectory.events]
    assert sum(len(p.trajectory.events) for p in out[True].parcels) > 100


def _ticks(batch: bool, field, ys, seconds: float, period: float = 0.01):
    """Advance a plant of SPEC parcels tick by tick, as a networked run does; returns the plant and the states."""
    plant = Plant(CELLS, [SPEC] * len(ys), LAWS["viscous"], integration=Integration(batch=batch))
    ys, active = [y.copy() for y in ys], [True] * len(ys)
    trail = []
    for k in range(int(round(seconds / period))):
        plant.advance(ys, active, field, k * period, (k + 1) * period, period)
        trail.append(np.array(ys))
    return plant, np.array(trail)


def test_supports_shared_by_weight_go_with_the_last_parcel_of_that_weight():
    """A long run holds memory for the parcels on the array: a parcel that leaves drops its share of the solved
    supports once no parcel of its weight is left (the others of its weight keep using them)."""
    heavy = parcel.rectangle(0.33, 0.24, 3.0, 0.8)
    specs = [SPEC, SPEC, heavy]
    plant = Plant(CELLS, specs, LAWS["viscous"])
    ys = [np.array([x, 0.55, 0.2, 0, 0, 0.0]) for x in (0.3, 0.75, 0.3)]
    ys[2][1] = 0.9
    plant.advance(ys, [True] * 3, _field(3), 0.0, 0.01, 0.01)
    light, big = (s.weight(9.81) for s in (SPEC, heavy))
    assert set(plant.shared_weights) == {light, big} and all(n > 0 for n in plant.shared_weights.values())
    plant.release(0)
    assert light in plant.shared_weights  # parcel 1 still shares them
    plant.release(1)
    plant.release(2)
    assert plant.shared_weights == {}
    assert plant.base[0].solves == 0 and plant.base[0].shared_solutions == {}  # fresh, and its own


def test_parcels_pushing_each_other_agree_with_and_without_batching():
    """A parcel driven into a resting one: quiet windows, then windows stepped as a group, then quiet again."""
    field = np.where(CELLS.positions[:, :1] < 0.6, [[0.3, 0.0]], [[0.0, 0.0]])
    ys = [np.array([0.3, 0.55, 0, 0, 0, 0.0]), np.array([0.75, 0.55, 0, 0, 0, 0.0])]
    off, a = _ticks(False, field, ys, 1.5)
    on, b = _ticks(True, field, ys, 1.5)
    np.testing.assert_array_equal(a, b)
    assert on.record.parcel_contacts == off.record.parcel_contacts == 1
    assert on.record.grouped_steps == off.record.grouped_steps > 0 and on.record.quiet_steps > 50
    assert b[-1, 1, 0] > 0.8  # the resting parcel was pushed along


def test_a_cell_taken_out_from_under_a_quiet_parcel_is_seen():
    """set_present drops every anchor: the next window is solved on the supports that remain."""
    field = _field(2)
    y0 = np.array([0.55, 0.55, 0.0, 0.0, 0.0, 0.0])
    ends = {}
    for batch in (False, True):
        plant = Plant(CELLS, [SPEC], LAWS["viscous"], integration=Integration(batch=batch))
        ys, active = [y0.copy()], [True]
        plant.advance(ys, active, field, 0.0, 0.01, 0.01)
        under = plant.base[0].support_at(ys[0])
        present = np.ones(CELLS.n, bool)
        present[under[0]] = False
        plant.set_present(present)
        plant.advance(ys, active, field, 0.01, 0.02, 0.01)
        assert plant.record.quiet_steps == (2 if batch else 0)
        ends[batch] = ys[0]
    np.testing.assert_allclose(ends[True], ends[False], rtol=0, atol=1e-15)
    plant = Plant(CELLS, [SPEC], LAWS["viscous"])
    ys = [y0.copy()]
    plant.advance(ys, [True], field, 0.0, 0.01, 0.01)
    plant.advance(ys, [True], field, 0.01, 0.02, 0.01)
    assert np.max(np.abs(ys[0] - ends[True])) > 1e-9  # the missing cell changed the motion


def test_a_plant_refuses_wheel_velocities_it_cannot_use():
    """Velocities are checked once a tick for the whole array (the per-parcel copies trust that check)."""
    plant = Plant(CELLS, [SPEC], LAWS["viscous"])
    ys = [np.array([0.55, 0.55, 0.0, 0.0, 0.0, 0.0])]
    bad = _field(2)
    bad[3, 1] = np.nan
    for velocities in (bad, _field(2)[:-1], _field(2)[:, :1]):
        with pytest.raises(ValueError, match="finite floats with shape"):
            plant.advance(ys, [True], velocities, 0.0, 0.01, 0.01)
    assert ys[0][3] == 0.0  # nothing moved


@pytest.mark.parametrize("batch", [True, False])
def test_a_plant_refuses_states_and_modes_it_cannot_use(batch):
    """The states of the active parcels are checked once a call (the engine behind the plant trusts that check,
    batched or not), and an integration mode when it is made."""
    plant = Plant(CELLS, [SPEC, SPEC], LAWS["viscous"], integration=Integration(batch=batch))
    good = np.array([0.55, 0.55, 0.0, 0.0, 0.0, 0.0])
    for bad in (np.array([0.55, np.nan, 0.0, 0.0, 0.0, 0.0]), np.array([0.55, 0.55, 0.0, 0.0, 0.0])):
        ys = [good.copy(), bad]
        with pytest.raises(ValueError, match="six finite numbers"):
            plant.advance(ys, [True, True], _field(2), 0.0, 0.01, 0.01)
        assert ys[0].tolist() == good.tolist()  # nothing moved
        plant.advance(ys, [True, False], _field(2), 0.0, 0.01, 0.01)  # an inactive parcel's state is not read
    with pytest.raises(ValueError, match="mode must be 'event' or 'fixed'"):
        Integration(mode="rk45")


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_the_reach_of_many_parcels_at_once_is_each_parcels_own(law):
    """The checks bound many parcels' reach in one go, their anchors' cells padded to the widest: the same floats as
    for each parcel alone, anchored by a stepper of its own (no padding)."""
    model, Y = _pieces(LAWS[law], seed=3, n=12)
    Y[:, 2] = np.linspace(0.0, np.pi / 2, len(Y))  # turned: supports of different sizes, so some are padded
    stepper = QuietStepper(CELLS, [SPEC] * len(Y), LAWS[law], [SPEC.mu] * len(Y), 9.81, 1e-10, 1e-12)
    models = [model] * len(Y)
    for i, y in enumerate(Y):
        stepper.refresh(i, stepper.measure(i, models, y), models, model.velocities)
    sizes = {len(a.support) for a in stepper.anchors.values()}
    assert len(sizes) > 1
    together = stepper.reach(list(range(len(Y))), Y, 0.01, model.velocities, 0.3)
    for i, y in enumerate(Y):
        alone = QuietStepper(CELLS, [SPEC], LAWS[law], [SPEC.mu], 9.81, 1e-10, 1e-12)
        alone.refresh(0, alone.measure(0, [model], y), [model], model.velocities)
        r, accel = alone.reach([0], y[None], 0.01, model.velocities, 0.3)
        assert (r[0], accel[0]) == (together[0][i], together[1][i])


def test_the_stepper_sees_wheels_change_in_place_and_keeps_a_read_only_array():
    """Which cells' wheels changed: found in an array changed in place (the stepper keeps a copy of a writable one),
    and not looked for again in the same read-only array (a plant's, kept as it is)."""
    stepper = QuietStepper(CELLS, [SPEC], LAWS["viscous"], [SPEC.mu], 9.81, 1e-10, 1e-12)
    v = _field(1)
    assert stepper.changes == 0 and stepper.seen is None
    stepper.see(v)
    first = stepper.changes
    assert first == 1 and stepper.seen is not v and stepper.seen.tolist() == v.tolist()  # a copy of a writable one
    v[5, 1] += 0.1  # in place
    stepper.see(v)
    assert stepper.changes == first + 1 and stepper.changed_at[5] == first + 1
    assert stepper.changed_at[4] == first and stepper.changed_at[-1] == -1  # the sentinel stays
    frozen = v.copy()
    frozen.setflags(write=False)
    stepper.see(frozen)  # the same values: nothing changed, and the array itself is kept
    assert stepper.changes == first + 1 and stepper.seen is frozen
    stepper.see(frozen)
    assert stepper.changes == first + 1
    other = _field(2)
    other.setflags(write=False)
    stepper.see(other)
    assert stepper.changes == first + 2 and stepper.seen is other


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_an_anchor_measured_again_on_the_same_cells_keeps_its_constants(law):
    """Measured again where its clearances ran out, an anchor on the same cells and solved pattern keeps the
    constants made for them (the wheels have not changed), and under Coulomb the largest drive they bound its reach
    with; on other cells it has none until the checks make them."""
    model = ParcelModel(CELLS, SPEC, _field(1), LAWS[law])
    stepper = QuietStepper(CELLS, [SPEC], LAWS[law], [SPEC.mu], 9.81, 1e-10, 1e-12)
    y0 = np.array([0.55, 0.52, 0.3, 0.05, 0.0, 0.1])
    first = stepper.measure(0, [model], y0)
    stepper.see(model.velocities)
    stepper.refresh(0, first, [model], model.velocities)
    drive = stepper.columns.drive[0]
    assert (drive > 0) == (law == "coulomb")
    nudged = y0 + np.array([1e-4, 0.0, 0.0, 0.0, 0.0, 0.0])  # the same cells under it
    again = stepper.measure(0, [model], nudged)
    assert np.array_equal(again.support, first.support)
    assert again.constants is first.constants and again.row == first.row
    assert stepper.columns.made[0] == stepper.changes and stepper.columns.drive[0] == drive
    moved = y0 + np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])  # a pitch along: other cells
    elsewhere = stepper.measure(0, [model], moved)
    assert not np.array_equal(elsewhere.support, first.support)
    assert elsewhere.constants is None and stepper.columns.made[0] == -1 and stepper.columns.drive[0] == 0.0


def test_an_anchor_measured_again_takes_its_solution_again_only_where_the_cache_would_find_it():
    """Measured again on the same cells, an anchor takes its solution again when it was the first of its pattern's
    shared solutions and holds there: what the pattern cache finds (the same arrays). Where it does not hold, or was
    not the first, the cache is asked."""
    from virtual_vehicle.engine.batch import anchor

    model = ParcelModel(CELLS, SPEC, _field(1), LAWS["viscous"])
    y0 = np.array([0.55, 0.52, 0.3, 0.05, 0.0, 0.1])
    first = anchor(model, y0, 1.0)
    assert first.first and model.solves == 1
    nudged = y0 + np.array([1e-4, 0.0, 0.0, 0.0, 0.0, 0.0])  # the same cells, the same contacts
    again = anchor(model, nudged, 1.0, first)
    assert again.solution is first.solution and again.first
    found = model.solution_for(again.support, nudged[:2])
    assert found.force_lin is again.solution.force_lin and np.array_equal(found.origin, again.solution.origin)
    assert anchor(model, nudged, 1.0).slack == again.slack and anchor(model, nudged, 1.0).clear == again.clear
    not_first = anchor(model, y0, 1.0)
    not_first.first = False  # as though another solution of the pattern came before it
    assert anchor(model, nudged, 1.0, not_first).solution is not not_first.solution  # asked the cache
    first.solution.__dict__["holds"] = lambda xi: False  # as though its contacts had changed there
    assert anchor(model, nudged, 1.0, first).solution is not first.solution  # asked the cache
    (solutions,) = model.shared_solutions.values()
    decoy = solutions[0].at(solutions[0].origin)
    decoy.__dict__["holds"] = lambda xi: False
    solutions.insert(0, decoy)  # another solution of the pattern, tried first
    assert not anchor(model, nudged, 1.0).first


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_a_parcel_handed_to_the_engine_brings_its_anchors_piece(law):
    """A parcel that goes to the event engine brings its anchor's piece (support, solution and constants made for
    the wheels under it now), which the engine looks up instead of making again: the very piece it would make. A
    parcel whose wheels changed since its constants were made brings nothing."""
    model = ParcelModel(CELLS, SPEC, _field(1), LAWS[law])
    stepper = QuietStepper(CELLS, [SPEC], LAWS[law], [SPEC.mu], 9.81, 1e-10, 1e-12)
    y0 = np.array([0.55, 0.52, 0.3, 0.05, 0.0, 0.1])
    stepper.step([model], [model], [0], [y0], model.velocities, 0.0, 0.01, np.array([0.0, 0.01]))
    a = stepper.anchors[0]
    engine = model.with_velocities(model.velocities)  # a copy with nothing cached, as a plant makes each tick
    assert stepper.hand_over(0, engine) is None  # no state: its cells not given
    cells = stepper.hand_over(0, engine, y0)  # measured at this pose: the cells under it
    assert cells.tolist() == engine.support_at(y0).tolist()
    assert stepper.hand_over(0, engine, y0 + np.array([1e-9, 0, 0, 0, 0, 0])) is None  # elsewhere: not given
    assert stepper.hand_over(0, engine, y0 + np.array([0, 0, 0, 1.0, 0, 0])) is not None  # velocities do not matter
    piece = engine.piece_at(y0)
    assert piece.constants is a.constants and piece.solution is a.solution and engine.pieces_cached == 1
    made = ParcelModel(CELLS, SPEC, _field(1), LAWS[law]).piece_at(y0)  # made afresh
    assert piece.key == made.key and piece.row == made.row
    assert piece.key == (tuple(piece.support.tolist()), tuple(piece.support[piece.solution.in_contact].tolist()))
    stepper.see(_field(2))  # new wheels, before the checks remake the anchor's constants
    later = model.with_velocities(_field(2))
    stepper.hand_over(0, later)
    assert later.pieces_cached == 0


def test_the_fastest_wheel_is_found_once_a_set_of_velocities_and_given_to_the_planner_and_the_stepper():
    """The planner and the quiet stepper take the fastest contact speed the plant found once for these velocities
    (what each would find), and find it themselves when not given it (the viscous law's bound, taken from rest:
    the planner otherwise measures speeds against the wheels' common velocity)."""
    from dataclasses import dataclass

    from virtual_vehicle.physics.laws import ViscousLaw

    @dataclass(frozen=True)
    class FromRest(ViscousLaw):
        galilean = False

    v = _field(4)
    plant = Plant(CELLS, [SPEC, SPEC], FromRest())
    models = plant.models(v)
    assert models.wheel_speed == wheel_speed_of(v) == float(np.sqrt((v ** 2).sum(axis=1)).max())
    assert wheel_speed_of(np.zeros((0, 2))) == 0.0
    ys = [np.array([0.35, 0.35, 0.0, 0.1, 0.0, 0.0]), np.array([0.75, 0.75, 0.2, 0.0, 0.1, 0.0])]
    assert plant.plan(ys, [True, True], v, 0.0, 0.5) == plant.plan(ys, [True, True], v, 0.0, 0.5, models.wheel_speed)
    assert plant.plan(ys, [True, True], v, 0.0, 0.5, 10 * models.wheel_speed)[0] < plant.plan(ys, [True, True], v,
                                                                                                0.0, 0.5)[0]


def test_chatter_steps_add_up_across_control_ticks():
    """A parcel at rest with two edges exactly on cell centres chatters (see test_dynamics): the fixed steps the
    engine takes across it are counted per tick and summed over the run, as a networked run records them."""
    from virtual_vehicle.run.sim import ParcelTrack

    hl, hw = SPEC.half_extents
    field = np.random.default_rng(7).uniform(-0.3, 0.3, (CELLS.n, 2))
    plant = Plant(CELLS, [SPEC], LAWS["viscous"], integration=Integration(dt=1e-4))
    ys, active, track, counts = [np.array([0.4 + hl, 0.4 + hw, 0.0, 0.0, 0.0, 0.0])], [True], ParcelTrack(), []
    for k in range(3):
        tr = plant.advance(ys, active, field, 0.01 * k, 0.01 * (k + 1), 0.01)[0]
        counts.append(tr.stats.get("chatter_steps", 0))
        track.add(tr, np.array([0.01 * k, 0.01 * (k + 1)]))
    assert counts[0] > 0 and plant.record.quiet_steps < 3  # the first tick chatters: never called quiet
    assert track.trajectory().stats["chatter_steps"] == sum(counts)


def _piece(kind: str, t: float, n: int, rng) -> Trajectory:
    """A tick's piece as the plant returns it: an event piece (its stats plain, with counts the run sums, or none)."""

    times = np.array([t, t + 0.005, t + 0.01])
    states = rng.normal(size=(3, 6))
    stats = {"plain": {"solves": n, "pieces_cached": 2}, "summed": {"solves": n, "chatter_steps": n + 1,
                                                                    "kinetic_start": 0.5 * n},
             "none": {}}[kind]
    events = [Event(t + 0.004, "support", tuple(states[1].tolist()), entered=(n,))] if kind != "none" else []
    return Trajectory(times, states, events, "completed", t + 0.01, 2, 30 + n, stats)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from(["quiet", "plain", "summed", "none"]), min_size=1, max_size=12),
       st.lists(st.booleans(), min_size=12, max_size=12), st.integers(0, 2**32 - 1))
@example(["quiet", "none"], [False] * 12, 0)  # a piece without stats leaves the quiet step's standing
@example(["summed", "quiet", "none", "plain"], [True] * 12, 1)  # summed counts carried across a quiet step
@example(["quiet", "summed", "quiet"], [False, True] * 6, 2)
def test_a_track_takes_quiet_steps_from_their_block_as_it_takes_their_trajectories(kinds, sampled, seed):
    """A networked run takes a tick the quiet stepper alone took straight from the stepper's block
    (ParcelTrack.add_quiet), without making its Trajectory: the parcel's trajectory at the end is the same in every
    field as when each tick's Trajectory is taken in (samples on the grid, events, counts, the stats the run sums
    and those the latest piece sets), whatever pieces come before and after."""
    from virtual_vehicle.engine.batch import QuietSteps
    from virtual_vehicle.run.sim import ParcelTrack

    rng = np.random.default_rng(seed)
    by_block, by_piece = ParcelTrack(), ParcelTrack()
    for k, kind in enumerate(kinds):
        t = 0.01 * k
        grid = np.array([t + 0.005]) if sampled[k] else np.empty(0)
        if kind == "quiet":
            times = np.array([t, t + 0.005, t + 0.01])
            states = rng.normal(size=(3, 3, 6))
            steps = QuietSteps([7, 4], times, states, [2, 0], 11, [k, k + 5])
            by_block.add_quiet(steps, 1, grid)
            by_piece.add(steps.trajectory(1), grid)
        else:
            tr = _piece(kind, t, k, rng)
            by_block.add(tr, grid)
            by_piece.add(tr, grid)
        assert by_block.started and by_block.piece.states.tolist() == by_piece.piece.states.tolist()
    mine, ref = by_block.trajectory(), by_piece.trajectory()
    assert mine.times.tolist() == ref.times.tolist() and mine.states.tolist() == ref.states.tolist()
    assert (mine.events, mine.status, mine.t_end, mine.segments, mine.rhs_evals, mine.stats) == \
        (ref.events, ref.status, ref.t_end, ref.segments, ref.rhs_evals, ref.stats)


