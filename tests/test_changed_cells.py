"""Stepping only the cells that changed (issue 8, performance): a stationary cell program run on the cells whose
sensors, sentences or state changed since the last tick, and ideal rounds that carry again only what changed, give
the same run to the last bit as stepping every cell and carrying every sentence."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.cells.network.delivery import IdealRounds
from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import CellInputs, ChangedCells, check_program, tree_map
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.cells.network.topology import from_layout
from virtual_vehicle.cells.sorting.policy import ASK, LATE, LOSSY, WEAK, YIELD
from virtual_vehicle.config.scenario import CellChange, FaultEvent, ReconfigurationSpec, load_scenario
from virtual_vehicle.model import layout
from virtual_vehicle.run.sim import LatencyStats, NetworkRun
from sorter_oracle import step_arrays, stepped_by_arrays

WALL = [j * 24 + 12 for j in range(2, 10)]  # sorting_junction: a wall across the middle, rows 2..9 of column 12


def _scenario(name: str, duration: float, control=None, **update):
    sc, _ = load_scenario(name)
    sensors = sc.sensors.model_copy(update={"record": True, **update.pop("sensors", {})})
    return sc.model_copy(update={"duration": duration, "sensors": sensors,
                                 "control": sc.control.model_copy(update=control or {}), **update})


CASES = {
    "merge, noisy sensors": lambda: _scenario("merge_two_streams", 6.0, sensors={"false_positive": 0.002,
                                                                                 "false_negative": 0.01}),
    "sequencing, parking, one-way cells": lambda: _scenario("reorder_stream", 8.0),
    "cells taken out and back, faults": lambda: _scenario(
        "sorting_junction", 5.0,
        reconfiguration=ReconfigurationSpec(changes=[CellChange(t=1.0, remove=WALL), CellChange(t=3.0, add=WALL)]),
        faults=load_scenario("sorting_junction")[0].faults.model_copy(update={"events": [
            FaultEvent(t=2.0, dead_cells=[100], dead_links=[(60, 0)], stuck_on=[(200, 0)])]})),
    "lossy rounds": lambda: _scenario("sorting_junction", 4.0, control={"loss_rate": 0.002}),
    "very lossy rounds": lambda: _scenario("sorting_junction", 3.0, control={"loss_rate": 0.05, "heartbeat": 0.0}),
    "lossy rounds, heartbeat": lambda: _scenario("sorting_junction", 3.0, control={"loss_rate": 0.05}),
    "hexagonal cells, lossy rounds": lambda: _scenario("hex_sorting_junction", 3.0, control={"loss_rate": 0.002}),
}


def _same_run(a, b) -> None:
    for p, q in zip(a.parcels, b.parcels, strict=True):
        np.testing.assert_array_equal(p.trajectory.times, q.trajectory.times)
        np.testing.assert_array_equal(p.trajectory.states, q.trajectory.states)
        assert repr(p.trajectory.events) == repr(q.trajectory.events)
    for k, v in a.network.per_tick.items():
        np.testing.assert_array_equal(v, b.network.per_tick[k], err_msg=k)
    for k, v in a.network.per_cell.items():
        np.testing.assert_array_equal(v, b.network.per_cell[k], err_msg=k)
    assert a.network.latency == b.network.latency
    for k, v in vars(a.cell_log).items():
        np.testing.assert_array_equal(v, vars(b.cell_log)[k], err_msg=k)


@pytest.mark.parametrize("case", list(CASES))
def test_stepping_only_the_cells_that_changed_gives_the_same_run(case):
    sc = CASES[case]()
    jobs = {flag: NetworkRun(sc.model_copy(update={"control": sc.control.model_copy(
        update={"changed_only": flag})}).build()) for flag in (True, False)}
    res = {flag: job.run(None) for flag, job in jobs.items()}
    assert jobs[False].stepper is None
    some = jobs[True].stepper
    n = jobs[True].setup.cells.n
    assert some.ticks == jobs[True].ticks
    if case == "very lossy rounds":  # every cell says everything every tick and hears something new: it gave up
        # comparing for a while
        assert some.backoff == some.max_backoff and some.stepped == n * some.ticks
    else:
        assert some.stepped < 0.5 * n * some.ticks  # most cells were not stepped: the comparison means something
    _same_run(res[True], res[False])
    for name, v in jobs[False].state.items():
        if not isinstance(v, dict):
            np.testing.assert_array_equal(v, jobs[True].state[name], err_msg=name)


def test_a_run_stepping_only_changed_cells_resumes_from_its_checkpoint_to_the_same_run(tmp_path):
    from virtual_vehicle.run.sim import resume, run_network

    setup = CASES["merge, noisy sensors"]().build()
    whole = run_network(setup, checkpoint=tmp_path / "c.ckpt", checkpoint_every=4.0)
    _same_run(whole, resume(tmp_path / "c.ckpt"))


def _topology(draw, nx, ny):
    topo = from_layout(layout.grid(nx, ny, 0.1))
    dead = draw(st.lists(st.integers(0, topo.n - 1), max_size=3, unique=True))
    links = draw(st.lists(st.tuples(st.integers(0, topo.n - 1), st.integers(0, 3)), max_size=4, unique=True))
    return topo.with_faults(dead_cells=dead, dead_links=[(c, p) for c, p in links if topo.neighbor[c, p] >= 0])


SCHEMA = Schema.of(a=(1, WordType.I16), b=(2, WordType.U8), c=(3, WordType.BOOL), d=(4, WordType.U16),
                   e=(5, WordType.I32), f=(6, WordType.F32))  # every word type


@settings(max_examples=40, deadline=None)
@given(st.data())
def test_ideal_rounds_carrying_only_what_changed_deliver_what_carrying_everything_does(data):
    nx, ny = data.draw(st.integers(1, 6)), data.draw(st.integers(1, 6))
    topo = _topology(data.draw, nx, ny)
    n = topo.n
    full, part = IdealRounds(topo), IdealRounds(topo)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    box = Mailbox.empty(SCHEMA, n, 4)
    inbox_b = None
    for tick in range(data.draw(st.integers(1, 8))):
        if tick == 3:  # the links change: both carry everything once more
            topo = _topology(data.draw, nx, ny)
            full.set_topology(topo)
            part.set_topology(topo)
        changed = rng.random(n) < data.draw(st.sampled_from([0.0, 0.1, 0.5, 1.0]))
        box.present[changed] = rng.random((changed.sum(), 4)) < 0.8
        for k, v in box.values.items():
            v[changed] = rng.integers(0, 100, (changed.sum(), 4))
        before = None if inbox_b is None else [a.copy() for a in (inbox_b.present, *inbox_b.values.values())]
        told = None if data.draw(st.integers(0, 3)) == 0 else changed  # sometimes the sender cannot tell
        inbox_a, stats_a = full.exchange(box, 0.01 * tick, 0.01)
        inbox_b, stats_b, inbox_changed = part.exchange_changed(box, told, 0.01 * tick, 0.01)
        assert (inbox_changed is None) == (told is None)
        np.testing.assert_array_equal(inbox_a.present, inbox_b.present)
        for k, v in inbox_a.values.items():
            np.testing.assert_array_equal(v, inbox_b.values[k])
        for k in ("sent", "received", "bytes_sent", "bytes_received", "latencies"):
            np.testing.assert_array_equal(getattr(stats_a, k), getattr(stats_b, k))
        assert (stats_a.lost, stats_a.unaddressed) == (stats_b.lost, stats_b.unaddressed)
        if before is not None and told is not None:  # the cells it says heard something new are those that did
            now = [inbox_b.present, *inbox_b.values.values()]
            differs = np.zeros(n, bool)
            for x, y in zip(before, now):
                differs |= (x != y).any(axis=1)
            np.testing.assert_array_equal(inbox_changed, differs)


class _Clock:
    """Says the time: its outputs change every tick while its state never does (not stationary)."""

    schema = Schema.of(x=(1, WordType.I16))
    stationary = True

    def init(self, n, ports, config):
        return {"seen": np.zeros(n, dtype=np.int64)}

    def step(self, state, inputs):
        n, P = inputs.connected.shape
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, x=np.zeros(n))
        return state, out, np.full((n, 2), inputs.t)


class _Census(_Clock):
    """Counts the cells it is stepped with (not local: a cell stepped alone sees other numbers)."""

    def step(self, state, inputs):
        n, P = inputs.connected.shape
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, x=np.full(n, n))
        return state, out, np.zeros((n, 2))


def test_the_contract_checker_catches_programs_that_are_not_stationary():
    topo = from_layout(layout.grid(5, 4, 0.1))
    for cheat in (_Clock(), _Census()):
        with pytest.raises(AssertionError, match="not stationary"):
            check_program(cheat, topo, {}, ticks=4)


def test_changed_cells_takes_stationary_programs_with_per_cell_arrays_only():
    from virtual_vehicle.cells.network.programs import Routing

    with pytest.raises(ValueError, match="stationary"):
        ChangedCells(Routing())

    class Lists(_Clock):
        def init(self, n, ports, config):
            return {"names": ["cell"] * n}

    topo = from_layout(layout.grid(3, 3, 0.1))
    inputs = CellInputs(0.0, np.zeros((9, 1), bool), Mailbox.empty(Lists.schema, 9, 4), topo.connected)
    with pytest.raises(TypeError, match="per-cell arrays"):
        ChangedCells(Lists()).step(Lists().init(9, 4, {}), inputs)


@pytest.mark.parametrize("value", [0.01, 1e-6, 1e-7, 2e3, float(LatencyStats.EDGES[100]),
                                   float(LatencyStats.EDGES[101]) * (1 - 1e-16)])
def test_latencies_all_alike_are_binned_as_any_others(value):
    one, many = LatencyStats(), LatencyStats()
    same = np.full(37, value)
    one.add(same)
    bins = np.clip(np.searchsorted(LatencyStats.EDGES, same, side="right") - 1, 0, 511)  # the general rule
    many.counts += np.bincount(bins, minlength=512)
    np.testing.assert_array_equal(one.counts, many.counts)
    assert (one.count, one.min, one.max) == (37, value, value)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 30), st.sampled_from([(), (1,), (2,), (3,), (4,), (5,), (8,), (2, 3), (4, 2)]),
       st.sampled_from([np.int64, np.int16, np.uint8, np.bool_, np.float64]), st.booleans(), st.integers(0, 2**32 - 1))
def test_rows_that_differ_are_found_in_any_shape_and_layout(m, shape, dtype, fortran, seed):
    from virtual_vehicle.cells.network.messages import rows_differ

    rng = np.random.default_rng(seed)
    x = rng.integers(0, 2, (m, *shape)).astype(dtype)
    y = np.where(rng.random(x.shape) < 0.05, 1 - x, x).astype(dtype)
    if fortran:
        x, y = np.asfortranarray(x), np.asfortranarray(y)
    expected = np.array([np.any(x[i] != y[i]) for i in range(m)], dtype=bool)
    np.testing.assert_array_equal(rows_differ([x, x], [y, x], m), expected)


class _Rows:
    """Stationary and local: each cell keeps one row of a (n, *shape) array of ``dtype`` (Fortran-ordered if
    ``fortran``) and, where a sensor is lit, rewrites it from a table indexed by its three sensors (for floats -0.0
    and, in float64, a NaN with a payload among the values); it says the index and drives at it. Stepped for only
    some cells, it hands its rows back as ``given_as`` (None: ``dtype``), as a program whose arithmetic promotes
    them might."""

    schema = Schema.of(x=(1, WordType.I16))
    stationary = True

    def __init__(self, n, shape, dtype, given_as, fortran):
        self.n, self.shape, self.dtype, self.given_as, self.fortran = n, shape, np.dtype(dtype), given_as, fortran
        table = np.arange(8.0) if self.dtype.kind != "b" else np.arange(8) % 2
        if self.dtype.kind == "f" and given_as is None:  # values that only bytes tell apart
            table[[1, 5]] = -0.0, 0.0
            if self.dtype == np.float64:
                table[6] = np.array(0x7FF4000000000ABC, np.uint64).view(np.float64)
        self.table = table.astype(self.dtype)

    def _order(self, a):
        return np.asfortranarray(a) if self.fortran else np.ascontiguousarray(a)

    def init(self, n, ports, config):
        return {"row": self._order(np.zeros((n, *self.shape), self.dtype))}

    def step(self, state, inputs):
        n, P = inputs.connected.shape
        code = np.asarray(inputs.sensors, np.int64) @ np.array([1, 2, 4])
        element = np.arange(int(np.prod(self.shape, dtype=np.int64))).reshape(self.shape)
        new = self.table[(code.reshape(-1, *[1] * len(self.shape)) + element) % 8]
        lit = (code > 0).reshape(-1, *[1] * len(self.shape))
        row = self._order(np.where(lit, new, state["row"]))
        if n < self.n and self.given_as is not None:
            row = self._order(row.astype(self.given_as))
        out = Mailbox.broadcast(self.schema, code > 0, P, x=code)
        return {"row": row}, out, np.stack([code, -code], axis=1).astype(float)


@settings(max_examples=80, deadline=None)
@given(st.integers(1, 40), st.sampled_from([(), (1,), (2,), (3,), (4,), (5,), (8,), (2, 3), (4, 2)]),
       st.sampled_from([np.int64, np.int32, np.int16, np.uint16, np.uint8, np.bool_, np.float64, np.float32]),
       st.sampled_from([None, np.int64, np.float64, np.int8]), st.booleans(), st.integers(0, 2**32 - 1))
def test_changed_cells_write_their_rows_back_as_assigning_them_would(n, shape, dtype, given_as, fortran, seed):
    """The rows of the changed cells are written into the state, sentences and wheel speeds ChangedCells keeps as
    assigning them would, bit for bit (a NaN's payload, -0.0), in any row shape and word type, also when the step
    hands them back in another dtype (cast as assignment casts them) and into state that is not C-contiguous: every
    tick the same as stepping every cell."""
    rng = np.random.default_rng(seed)
    topo = from_layout(layout.grid(n, 1, 0.1))
    program = _Rows(n, shape, dtype, given_as, fortran)
    some = ChangedCells(program, full_share=1.0)  # never gives up comparing: every tick after the first is partial
    state_a, state_b = program.init(n, 4, {}), program.init(n, 4, {})
    inbox = Mailbox.empty(program.schema, n, 4)
    sensors = np.zeros((n, 3), bool)  # the first tick (every cell) changes nothing; the next steps a proper subset
    for k in range(6):
        if k:
            redrawn = rng.choice(n, int(rng.integers(1, n)) if n > 1 else 1, replace=False)
            sensors = sensors.copy()
            sensors[redrawn] = rng.random((len(redrawn), 3)) < rng.choice([0.1, 0.3, 0.6])
        state_a, out_a, wheels_a = program.step(state_a, CellInputs(0.01 * k, sensors, inbox, topo.connected))
        state_b, out_b, wheels_b, _ = some.step(state_b, CellInputs(0.01 * k, sensors, inbox, topo.connected))
        a, b = state_a["row"], state_b["row"]
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        assert [x.tobytes() for x in out_a.arrays] == [x.tobytes() for x in out_b.arrays]
        assert np.asarray(wheels_a).tobytes() == np.asarray(wheels_b).tobytes()
    assert some.ticks == 6 and (n == 1 or some.stepped < 6 * n)  # rows were written back, not every cell stepped


class _Echo:
    """Stationary and local: a cell holds how many hops away (up to 5) a lit sensor is, and says so."""

    schema = Schema.of(x=(1, WordType.I16))
    stationary = True

    def init(self, n, ports, config):
        return {"v": np.full(n, 5, dtype=np.int64)}

    def step(self, state, inputs):
        n, P = inputs.connected.shape
        heard = np.where(inputs.inbox.present, inputs.inbox.values["x"].astype(np.int64) + 1, 5).min(axis=1)
        v = np.where(np.asarray(inputs.sensors)[:, 0], 0, np.minimum(heard, 5))
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, x=v)
        return {"v": v}, out, np.stack([v, -v], axis=1).astype(float)


def test_changed_cells_gives_up_comparing_in_turmoil_and_comes_back_when_it_calms():
    topo = from_layout(layout.grid(10, 10, 0.1))
    n, program = topo.n, _Echo()
    calm = np.zeros((n, 1), bool)
    calm[[12, 57]] = True
    rng = np.random.default_rng(5)
    some = ChangedCells(program, max_backoff=4)
    full_delivery, part_delivery = IdealRounds(topo), IdealRounds(topo)
    state_a = program.init(n, 4, {})
    state_b = program.init(n, 4, {})
    inbox_a = inbox_b = Mailbox.empty(program.schema, n, 4)
    inbox_changed = None
    plain, partial_after = [], []
    for k in range(40):
        sensors = rng.random((n, 1)) < 0.5 if 5 <= k < 20 else calm  # turmoil, then calm again
        state_a, out_a, wheels_a = program.step(state_a, CellInputs(0.01 * k, sensors, inbox_a, topo.connected))
        before = some.stepped
        state_b, out_b, wheels_b, out_changed = some.step(
            state_b, CellInputs(0.01 * k, sensors, inbox_b, topo.connected), inbox_changed)
        np.testing.assert_array_equal(wheels_a, wheels_b)
        np.testing.assert_array_equal(out_a.values["x"], out_b.values["x"])
        if out_changed is None:
            plain.append(k)
        elif k >= 25:
            partial_after.append(some.stepped - before)
        inbox_a, _ = full_delivery.exchange(out_a, 0.01 * k, 0.01)
        inbox_b, _, inbox_changed = part_delivery.exchange_changed(out_b, out_changed, 0.01 * k, 0.01)
        np.testing.assert_array_equal(inbox_a.values["x"], inbox_b.values["x"])
    # it stopped comparing in the turmoil (and at the start, when every inbox is new), not once it was calm
    assert any(5 < k < 20 for k in plain) and max(plain) < 30
    # and once calm again, stepped few cells every tick but one (the tick that compares again after giving up)
    assert len(partial_after) >= 10 and sum(c >= n // 2 for c in partial_after) <= 1
    assert some.backoff == 1  # the next turmoil starts with one tick of giving up again


def _same_step(mine, ref) -> None:
    """Two sorter steps' outputs are the same: state (keys in order, dtypes, values), sentences, wheel speeds."""
    (s1, o1, w1), (s2, o2, w2) = mine, ref
    assert list(s1) == list(s2) and list(s1["heard"]) == list(s2["heard"]) and list(s1["said"]) == list(s2["said"])
    for k in s1:
        for a, b in ([(s1[k][w], s2[k][w]) for w in s1[k]] if isinstance(s1[k], dict) else [(s1[k], s2[k])]):
            assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), k
    assert list(o1.values) == list(o2.values) and o1.present.tolist() == o2.present.tolist()
    assert (o1.words is None) == (o2.words is None)
    if o1.words is not None:  # partial sentences: the same words in each
        assert np.array_equal(o1.words, o2.words)
    for w in o1.values:
        assert o1.values[w].dtype == o2.values[w].dtype and np.array_equal(o1.values[w], o2.values[w]), w
    assert np.asarray(w1).dtype == np.asarray(w2).dtype and np.asarray(w1).tobytes() == np.asarray(w2).tobytes()


@pytest.mark.parametrize("case", list(CASES))
def test_the_compiled_sorter_runs_as_its_array_statement_in_whole_runs(case):
    """A whole run with the compiled sorter (stepping the changed cells in place, Sorter.step_rows, and every cell
    with Sorter.step on the ticks that step them all) is the same run as with its statement in array operations
    (the changed cells gathered, stepped and written back): trajectories, network record, every tick's sensors, wheel
    speeds and traffic, and the cells' state at the end. Merging under noisy sensors, sequencing with parking and
    one-way cells, cells taken out and back with faults, lossy and very lossy rounds (where neighbours' words age and
    holds outlive a tick)."""
    sc = CASES[case]()
    jobs, res, in_place = {}, {}, [0]
    for compiled in (True, False):
        setup = sc.build()
        program = setup.control.program
        if not compiled:
            stepped_by_arrays(program)
        else:
            step_rows = program.step_rows

            def counted(*args):
                out = step_rows(*args)
                in_place[0] += out is not None
                return out

            program.step_rows = counted
        jobs[compiled] = NetworkRun(setup)
        res[compiled] = jobs[compiled].run(None)
    _same_run(res[True], res[False])
    if case != "very lossy rounds":  # (there every cell is stepped, with Sorter.step)
        assert in_place[0] > 0.5 * jobs[True].stepper.ticks
    for name, v in jobs[False].state.items():
        pairs = [(v[w], jobs[True].state[name][w]) for w in v] if isinstance(v, dict) else [(v, jobs[True].state[name])]
        for a, b in pairs:
            np.testing.assert_array_equal(a, b, err_msg=name)


def _keys(rng, shape, P: int = 4) -> np.ndarray:
    """Direction keys as sorters say them (rules.direction_key: distance, keeping the direction, a port of ``P``,
    hops), or none."""
    key = ((rng.integers(0, 260, shape) * 2 + rng.integers(0, 2, shape)) * 8 + rng.integers(0, P, shape)) * 64 \
        + rng.integers(0, 64, shape)
    return np.where(rng.random(shape) < 0.3, 1 << 20, key)


def _said(rng, shape, P: int = 4) -> dict[str, np.ndarray]:
    """Words as sorters say them where a word packs two fields: a direction key, ``stop`` (hops to a stopping cell
    and the port it was heard through above six bits, five on a hexagonal cell, then hops to a parking cell; 255
    for none) and ``ack`` (a run of held cells, then the port asked through plus one, then the ports that lead to a
    dead neighbour: 8 + 4 + 4 bits, 7 + 3 + 6 on a hexagonal cell), on cells of ``P`` ports."""
    hops = lambda: np.where(rng.random(shape) < 0.4, 255, rng.integers(0, 10, shape))  # noqa: E731
    stop = hops()
    stop = np.where(stop < 255, stop + (rng.integers(0, P, shape) << (6 if P == 4 else 5)), stop)
    rb, pb = (8, 4) if P == 4 else (7, 3)
    return {"key": _keys(rng, shape, P), "stop": stop + (hops() << 8),
            "ack": rng.integers(0, 5, shape) + (rng.integers(0, P + 1, shape) << rb)
            + np.where(rng.random(shape) < 0.5, rng.integers(0, 1 << P, shape) << (rb + pb), 0)}


_WORDS = {"d": (-2**31, 2**31 - 1), "nxt": (0, 6), "vid": (-1, 8), "goal": (-1, 40), "key": (0, 1 << 20),
          "stop": (0, 2**16 - 1), "req": (-1, 8), "rdep": (0, 4), "hold": (-1, 8), "ack": (0, 2**16 - 1),
          "ex": (-2, 3), "blk": (-2**31, 2**31 - 1)}


def _random_sorter_inputs(rng, max_age: int, parking: bool, labelled: bool, partial: bool = False, P: int = 4,
                          asks: float = 0.2, late: float = 0.3):
    """A sorter, a state and inputs drawn at random (see the test below); ``partial``: a sorter that sends only the
    words that changed, hearing sentences that carry some words only; ``P`` ports a cell (6: hexagonal); ``asks``:
    the share of arriving sentences that ask the cell to say everything again; ``late``: the share of requests
    heard, arriving and held that a late vehicle made (marked LATE)."""
    from virtual_vehicle.cells.network.messages import DTYPE
    from virtual_vehicle.cells.sorting import Sorter

    n = 40
    program = Sorter(0.3, gap=int(rng.integers(1, 4)), reach=int(rng.integers(2, 9)), max_age=max_age,
                     heartbeat=0.03 if partial else float(rng.choice([0.0, 0.03])),  # every tick, or every third
                     partial=partial)
    state = program.init(n, P, {})
    for w, (lo, hi) in _WORDS.items():
        state["heard"][w] = rng.integers(lo, hi + 1, (n, P))
    state["heard"].update(_said(rng, (n, P), P))
    t = float(rng.integers(0, 10**5)) * 0.01
    # the tick each port last heard (4 and 7 ticks ago: a missed heartbeat, the ask window for max_age 0 and 3)
    state["heard_at"] = round(t / 0.01) - rng.choice([0, 1, 2, 4, 5, 7, 2**40], (n, P))
    for w, (lo, hi) in _WORDS.items():  # what was last said on each port: some words as they will be, some not
        state["said"][w] = np.where(rng.random((n, P)) < 0.3, -(1 << 40), rng.integers(lo, hi + 1, (n, P)))
    state["again"] = rng.choice([0, 0, 1, 2], (n, P))
    if partial:  # the words a port repeats, kept above the count
        state["again"] += np.where(state["again"] > 0, rng.integers(0, 1 << 12, (n, P)) << 16, 0)
    state["again"] += np.where(rng.random((n, P)) < 0.3, LOSSY, 0)  # links marked lossy (an ask sent or heard)
    for k, (lo, hi) in {"vid": (-1, 8), "goal": (-1, 40), "dir": (-1, P - 1), "back": (0, 6), "bdir": (-1, P - 1),
                        "hold": (-1, 8), "hage": (0, 4), "hport": (-1, P - 1), "hdep": (0, 4),
                        "nxt": (0, 6)}.items():
        state[k] = rng.integers(lo, hi + 1, n)
    inbox = Mailbox.empty(program.schema, n, P)
    inbox.present[:] = rng.random((n, P)) < 0.7
    for f in program.schema.fields:
        lo, hi = _WORDS[f.name]
        info = np.iinfo(DTYPE[f.type])
        inbox.values[f.name][:] = rng.integers(max(lo, info.min), min(hi, info.max) + 1, (n, P))
    for w, v in _said(rng, (n, P), P).items():
        inbox.values[w][:] = v
    inbox.values["ex"][:] += np.where(rng.random((n, P)) < asks, ASK, 0)  # neighbours asking to hear everything again
    if partial:  # each sentence carries some of the words
        inbox.words = rng.integers(0, 1 << 12, (n, P))
    config = {"exit": rng.choice([-1, -1, -1, 0, 1, 2, 3], n), "exit_port": rng.integers(-1, P, n),
              "entry": rng.random(n) < 0.2, "entry_no": rng.integers(0, 3000, n),
              "forbid": rng.choice([-1, -1, *range(P)], n)}
    if parking:
        config["park"] = rng.random(n) < 0.2
    labels = rng.integers(-1, 40, n) if labelled else None
    connected = rng.random((n, P)) < 0.85
    config["inner"] = connected | (rng.random((n, P)) < 0.5)  # some silent ports lead to dead cells
    inputs = CellInputs(t, rng.random((n, 5)) < 0.4, inbox, connected, config, labels)
    # requests marked by a vehicle giving way (rdep's high bit), heard, arriving and held, and back-offs from a
    # younger asker (bdir marked WEAK), drawn last, so that the draws above are as they were
    state["heard"]["rdep"] = state["heard"]["rdep"] + np.where(rng.random((n, P)) < 0.3, YIELD, 0)
    inbox.values["rdep"][:] += np.where(rng.random((n, P)) < 0.3, YIELD, 0).astype(inbox.values["rdep"].dtype)
    state["hdep"] = state["hdep"] + np.where(rng.random(n) < 0.3, YIELD, 0)
    state["bdir"] = np.where((state["bdir"] >= 0) & (rng.random(n) < 0.3), state["bdir"] + WEAK, state["bdir"])
    # requests marked by a late vehicle (rdep's LATE bit), heard, arriving and held, from a generator of their own
    # (spawned: it draws nothing from ``rng``), so that every draw above and after is as it was
    marks = rng.spawn(1)[0]
    state["heard"]["rdep"] = state["heard"]["rdep"] + np.where(marks.random((n, P)) < late, LATE, 0)
    inbox.values["rdep"][:] += np.where(marks.random((n, P)) < late, LATE, 0).astype(inbox.values["rdep"].dtype)
    state["hdep"] = state["hdep"] + np.where(marks.random(n) < late, LATE, 0)
    # the sensor each cell shares with the neighbour on a port (-1 none, some beyond the cell's five), from a
    # generator of its own again, so that every draw above is as it was
    config["sides"] = rng.spawn(1)[0].integers(-1, 7, (n, P))
    # a sorter that stops a vehicle at its exit lane's far side (or not), and the ticks each cell has stood there
    # (some at the end of a stop or of a pause), from a generator of their own again
    lanes = rng.spawn(1)[0]
    program.lane_hold = int(lanes.choice([0, 1, 2, 4]))
    state["lane"] = lanes.integers(0, 8, n)
    return program, state, inputs


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 3]), st.booleans(), st.booleans(), st.booleans())
def test_the_compiled_sorter_steps_as_its_array_statement_on_any_inputs(seed, max_age, parking, labelled, partial):
    """The same on random inputs a run may never give: any words heard or arriving (within their types; vehicle
    ids from a handful, so that neighbours share them; with ``partial``, sentences carrying any of the words), any
    sensors, links, labels, exits, entries, parking and one-way cells, and any state, stale or fresh."""
    program, state, inputs = _random_sorter_inputs(np.random.default_rng(seed), max_age, parking, labelled,
                                                   partial)
    _same_step(program.step(state, inputs), step_arrays(program, state, inputs))


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 3]), st.booleans(), st.booleans(), st.booleans())
def test_the_compiled_sorter_steps_as_its_array_statement_on_hexagonal_cells(seed, max_age, parking, labelled,
                                                                             partial):
    """The same on cells of six ports (a hexagonal lattice): the port across, the lane's sides, the hop counts
    packed in five bits beside a port of three, the wheels' velocity at 60-degree steps."""
    program, state, inputs = _random_sorter_inputs(np.random.default_rng(seed), max_age, parking, labelled,
                                                   partial, P=6)
    _same_step(program.step(state, inputs), step_arrays(program, state, inputs))


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 3]), st.booleans(), st.booleans())
def test_the_sorter_steps_changed_cells_in_place_as_it_steps_them_gathered(seed, max_age, parking, silent):
    """Sorter.step_rows on some rows of the full inputs writes into the state, sentences and wheel speeds exactly
    what stepping those rows gathered gives (and leaves the other rows as they were), and reports the rows whose
    state and whose sentences changed, as comparing them does. ``silent``: nothing arrives and nothing heard is
    trusted, from a state already stepped so, so that only a cell's own words (a back-off counting down, a hold
    ageing) can change."""
    from virtual_vehicle.cells.network.messages import rows_differ

    rng = np.random.default_rng(seed)
    program, state, inputs = _random_sorter_inputs(rng, max_age, parking, True)
    n = len(inputs.sensors)
    kept = [k for k in program.init(n, 4, {}) if k not in ("dist", "heard", "heard_at", "said", "again")]
    if silent:
        inputs.inbox.present[:] = False
        state["heard_at"][:] = -(1 << 40)
        state = {**program.step(state, inputs)[0], **{k: state[k] for k in kept}}  # heard, heard_at, dist, said
        state = {**program.step(state, inputs)[0], **{k: state[k] for k in kept}}  # settled
    out0, wheels0 = program.step(state, CellInputs(inputs.t, inputs.sensors, inputs.inbox, inputs.connected,
                                                   inputs.config, inputs.labels))[1:]
    rows = np.sort(rng.choice(n, int(rng.integers(1, n + 1)), replace=False))
    sub = CellInputs(inputs.t, inputs.sensors[rows], inputs.inbox.take(rows), inputs.connected[rows],
                     {k: v[rows] for k, v in inputs.config.items()}, inputs.labels[rows])
    sub_state = {k: ({w: a[rows] for w, a in v.items()} if isinstance(v, dict) else v[rows])
                 for k, v in state.items()}
    ref_state, ref_out, ref_wheels = step_arrays(program, sub_state, sub)
    mine = {k: ({w: a.copy() for w, a in v.items()} if isinstance(v, dict) else v.copy()) for k, v in state.items()}
    outbox = Mailbox(out0.schema, out0.present.copy(), {w: a.copy() for w, a in out0.values.items()})
    wheels = np.array(wheels0)
    unsettled, out_changed = program.step_rows(mine, inputs, rows, outbox, wheels)
    others = np.setdiff1d(np.arange(n), rows)

    def leaves(st):  # by name: init and step hold the words in different orders
        return [st["dist"], *(st["heard"][f.name] for f in program.schema.fields), st["heard_at"],
                *(st[k] for k in kept), *(st["said"][f.name] for f in program.schema.fields), st["again"]]

    for a, b, c in zip(leaves(mine), leaves(ref_state), leaves(state), strict=True):
        assert np.array_equal(a[rows], b) and np.array_equal(a[others], c[others])
    for a, b, c in zip(outbox.arrays, ref_out.arrays, out0.arrays):
        assert np.array_equal(a[rows], b) and np.array_equal(a[others], c[others])
    assert wheels[rows].tobytes() == np.asarray(ref_wheels).tobytes()
    assert np.array_equal(wheels[others], np.asarray(wheels0)[others])
    assert unsettled[others].sum() == out_changed[others].sum() == 0
    assert unsettled[rows].tolist() == rows_differ(leaves(ref_state), [a[rows] for a in leaves(state)],
                                                   len(rows)).tolist()
    assert out_changed[rows].tolist() == rows_differ(ref_out.arrays, [a[rows] for a in out0.arrays],
                                                     len(rows)).tolist()


def test_a_direction_key_naming_no_port_fails_in_both_sorters():
    """A key word no sorter says (its port field beyond the cell's four ports) fails the compiled step as it fails
    the array one, instead of reading past the cell's ports."""
    from virtual_vehicle.cells.sorting import Sorter

    n, P = 3, 4
    for compiled in (True, False):
        program = Sorter(0.3) if compiled else stepped_by_arrays(Sorter(0.3))
        state = program.init(n, P, {})
        state["vid"][:] = 7
        state["goal"][:] = 0
        inbox = Mailbox.empty(program.schema, n, P)
        inbox.present[:] = True
        inbox.values["vid"][:] = 7
        inbox.values["key"][:] = (5 * 8 + 6) * 64  # port 6
        inputs = CellInputs(0.0, np.ones((n, 5), bool), inbox, np.ones((n, P), bool), {}, None)
        with pytest.raises(IndexError):
            program.step(state, inputs)


def _leaves(st) -> list:
    """A state's arrays, in the order of its sorted keys (nested dicts flattened)."""
    return [a for k in sorted(st) for a in (_leaves(st[k]) if isinstance(st[k], dict) else [st[k]])]


def _whole_and_quiet(program, state, inputs, out, wheels, quiet, partial):
    """Step every row of the sorter ``program`` whole, and again (from copies of the same ``state``, sentences ``out``
    and ``wheels``) offering the rows ``quiet`` to the clocks-only path; assert both give the same state, sentences,
    wheels and masks. Returns the two runs' masks (whole first)."""
    n = len(quiet)
    runs = []
    for given_quiet in (None, quiet):
        mine = tree_map(np.copy, state)
        box = Mailbox(out.schema, out.present.copy(), {w: a.copy() for w, a in out.values.items()},
                      None if out.words is None else out.words.copy())
        w = wheels.copy()
        masks = program.step_rows(mine, inputs, np.arange(n), box, w,
                                  np.zeros(n, bool) if given_quiet is None else given_quiet)
        runs.append((_leaves(mine), box, w, masks))
    (ref_leaves, ref_box, ref_wheels, ref_masks), (leaves, box, w, masks) = runs
    for a, b in zip(leaves, ref_leaves, strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(box.arrays, ref_box.arrays, strict=True):
        np.testing.assert_array_equal(a, b)
    if partial:
        np.testing.assert_array_equal(box.words, ref_box.words)
    assert w.tobytes() == ref_wheels.tobytes()
    for a, b in zip(masks[:3], ref_masks[:3], strict=True):
        np.testing.assert_array_equal(a, b)
    return ref_masks, masks


def test_a_sorter_cell_whose_clocks_alone_run_ticks_them_as_its_whole_step_would():
    """Sorter.step_rows with ``quiet`` rows (their last step changed only their clocks, their sensors and labels are
    the same, the tick is not due for them) ticks only the clocks of those that hear nothing new, and that gives
    every state word, sentence, wheel speed and mask the whole step gives, on random states and inputs held for two
    ticks, then at the third (the one compared) some ports falling silent and some hearing a word changed; with and
    without parking cells, holds kept for a while and partial sentences. Some rows tick their clocks alone in these
    draws, and some quiet ones are stepped whole, or the comparison would mean nothing."""
    alone = whole = 0  # quiet rows that ticked their clocks alone, and that heard something new
    for seed in range(48):
        rng = np.random.default_rng(seed)
        max_age, parking, partial = [0, 3][seed % 2], bool(seed // 2 % 2), bool(seed // 4 % 2)
        program, state, inputs = _random_sorter_inputs(rng, max_age, parking, True, partial)
        n = len(inputs.sensors)

        def at(k, inbox=inputs.inbox):
            return CellInputs(inputs.t + k * program.period, inputs.sensors, inbox, inputs.connected,
                              inputs.config, inputs.labels)

        inbox = Mailbox(inputs.inbox.schema, inputs.inbox.present & (rng.random((n, 4)) < 0.7),
                        {w: a.copy() for w, a in inputs.inbox.values.items()},
                        None if inputs.inbox.words is None else inputs.inbox.words.copy())
        word = inbox.values[str(rng.choice(list(inbox.values)))]
        word[rng.random((n, 4)) < 0.1] += 1  # a word heard that the cell did not hold (where it arrives)

        state, out, wheels = program.step(state, inputs)
        out = Mailbox(out.schema, out.present.copy(), {w: a.copy() for w, a in out.values.items()},
                      None if out.words is None else out.words.copy())
        wheels = np.array(wheels)
        ticking = program.step_rows(state, at(1), np.arange(n), out, wheels, np.zeros(n, bool))[2]
        quiet = ticking & ~program.due(at(2).t, state, inputs.config)
        ref_masks, masks = _whole_and_quiet(program, state, at(2, inbox), out, wheels, quiet, partial)
        assert not ref_masks[3].any() and not (masks[3] & ~quiet).any()
        alone += int(masks[3].sum())
        whole += int((quiet & ~masks[3]).sum())
    assert alone > 30 and whole > 30


def test_a_sorter_cell_that_read_back_nothing_new_ticks_its_clocks_as_its_whole_step_would():
    """Sorter.step_rows given as ``quiet`` every row whose last step changed none of the state words the rules read
    back (what it heard and said, its gradients and other words computed afresh may have changed, or nothing), due
    or not: a row that hears nothing new ticks its clocks alone - also at its heartbeat or the tick after - and that
    gives every state word, sentence, wheel speed and mask the whole step gives, while a row whose trust in a silent
    neighbour runs out now, or that asks a neighbour to say everything again, is stepped whole. Random states,
    square and hexagonal cells; the first tick silent, the second hearing random words
    on most ports, the third (the one compared) mostly what the ports hold; heartbeats every third tick. Rows that
    ticked alone after hearing new words, rows at a heartbeat and rows whose trust ran out occur in these draws, or
    the comparison would mean nothing."""
    from virtual_vehicle.cells.sorting.rules import heartbeat_due, tick_of

    beats = stale = heard = 0  # rows ticked alone at a heartbeat / after hearing new words; quiet rows gone stale
    # (320 draws: since a parked vehicle gives way, fewer rows stand still, and 256 gave 29-30 rows at a heartbeat)
    for seed in range(320):
        rng = np.random.default_rng(1000 + seed)
        max_age, parking, partial = [0, 3][seed % 2], bool(seed // 2 % 2), bool(seed // 4 % 2)
        P = 6 if seed % 3 == 0 else 4  # some hexagonal cells
        # (no asks drawn: a row that hears one hears something new, stepped whole, as a row that hears new words)
        program, state, inputs = _random_sorter_inputs(rng, max_age, parking, True, partial, P, asks=0.0)
        program.heartbeat_ticks, program.trust = 3, max_age + 4  # (the draw may say every tick)
        program.repeats = 2
        n = len(inputs.sensors)
        tick = tick_of(inputs.t, program.period)
        state["heard_at"] = tick - rng.choice([0, 1, 2, 3, 5, 6, 2**40], (n, P))  # some run out at tick + 2

        def at(k, inbox=inputs.inbox):
            return CellInputs(inputs.t + k * program.period, inputs.sensors, inbox, inputs.connected,
                              inputs.config, inputs.labels)

        silent = Mailbox(inputs.inbox.schema, np.zeros_like(inputs.inbox.present), inputs.inbox.values,
                         inputs.inbox.words)
        state, out, wheels = program.step(state, at(0, silent))  # (silent: the trust drawn above runs on)
        out = Mailbox(out.schema, out.present.copy(), {w: a.copy() for w, a in out.values.items()},
                      None if out.words is None else out.words.copy())
        wheels = np.array(wheels)
        before = {w: a.copy() for w, a in state["heard"].items()}
        unsettled, _, ticking = program.step_rows(state, at(1), np.arange(n), out, wheels, np.zeros(n, bool))[:3]
        new_words = np.zeros(n, bool)
        for w, a in before.items():
            new_words |= (a != state["heard"][w]).any(axis=1)
        quiet = ticking | ~unsettled
        holds = rng.random((n, P)) < 0.8  # the ports that hear what they hold (if they hear), the others not
        inbox = Mailbox(inputs.inbox.schema, rng.random((n, P)) < 0.3,
                        {w: np.where(holds, state["heard"][w], a).astype(a.dtype)
                         for w, a in inputs.inbox.values.items()},
                        None if inputs.inbox.words is None else inputs.inbox.words.copy())
        due = program.due(at(2).t, state, inputs.config)
        ref_masks, masks = _whole_and_quiet(program, state, at(2, inbox), out, wheels, quiet, partial)
        number = inputs.config["entry_no"]
        beat = heartbeat_due(tick + 2, number, 3) | heartbeat_due(tick + 1, number, 3)
        runs_out = np.any(tick + 2 - state["heard_at"] == program.trust + 1, axis=1)
        assert not (masks[3] & runs_out).any()
        ago = tick + 2 - state["heard_at"]  # a row that asks a neighbour to say everything again sends: whole
        asking = np.any((ago > 3 + max_age) & (ago <= program.trust), axis=1) & (not partial)
        assert not (masks[3] & asking).any()
        beats += int((masks[3] & beat & due).sum())
        stale += int((quiet & runs_out).sum())
        heard += int((masks[3] & new_words).sum())
    assert beats > 30 and stale > 30 and heard > 30, (beats, stale, heard)
