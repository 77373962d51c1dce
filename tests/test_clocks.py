"""Every cell controller on its own clock (``[control.clock]``): no drift and no jitter is the synchronous run to the
last bit; with drift and jitter the cells tick when their clocks say, under both delivery models, checkpoints resume
exactly, and the sorter still delivers."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from virtual_vehicle.cells.network.clocks import ClockParams, Mailboxes
from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.config.scenario import load_scenario, parse_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import ClockedRun, FieldRun, NetworkRun, network_job, resume, run, run_kind
from virtual_vehicle.run.tasks import sorting_report


def _scenario(name: str, duration: float, **clock):
    sc, _ = load_scenario(name)
    control = sc.control.model_copy(update={"clock": type(sc.control.clock)(**clock)})
    return sc.model_copy(update={"duration": duration, "control": control})


def _same(a, b) -> None:
    for p, q in zip(a.parcels, b.parcels):
        assert p.trajectory.times.tobytes() == q.trajectory.times.tobytes()
        assert p.trajectory.states.tobytes() == q.trajectory.states.tobytes()
        assert p.trajectory.events == q.trajectory.events and p.entered_at == q.entered_at
    sa, sb = copy.deepcopy(a.summary()), copy.deepcopy(b.summary())
    for s in (sa, sb):
        s.pop("wall_time_s"), s.pop("real_time_factor")
        s["network"].pop("clocks", None)
    assert sa == sb
    for k, v in a.network.per_tick.items():
        assert v.tobytes() == b.network.per_tick[k].tobytes(), k


@pytest.mark.parametrize("name, duration", [("sorting_junction", 4.0), ("prototype_18_network", 1.5)])
def test_own_clocks_without_drift_or_jitter_are_the_synchronous_run_to_the_last_bit(name, duration):
    setup = _scenario(name, duration).build()
    assert setup.control.clock is None and type(NetworkRun(setup)) is NetworkRun  # the default: one shared clock
    own = dataclasses.replace(setup, control=dataclasses.replace(setup.control, clock=ClockParams()))
    job = ClockedRun(own)
    clocked = job.run()
    _same(run(setup), clocked)
    assert job.k == job.ticks  # one instant a period: every cell ticks at once
    assert clocked.summary()["network"]["clocks"]["cells_a_instant"] == setup.cells.n


def test_the_kind_a_checkpoint_is_checked_against_is_the_kind_of_run_the_scenario_makes():
    """Reading a checkpoint back refuses one whose scenario makes another kind of run (``run_kind``): that kind is
    the one ``network_job`` makes, on one shared clock and on the cells' own, and a constant field's."""
    shared = _scenario("prototype_18_network_ideal", 0.2).build()
    own = _scenario("prototype_18_network_ideal", 0.2, drift=0.01, jitter=0.001, seed=3).build()
    for setup, kind in ((shared, NetworkRun), (own, ClockedRun)):
        assert type(network_job(setup)) is kind and run_kind(setup) == kind.KIND
    assert run_kind(load_scenario("crossing_30x30")[0].build()) == FieldRun.KIND
    assert len({NetworkRun.KIND, ClockedRun.KIND, FieldRun.KIND}) == 3


@pytest.mark.parametrize("delivery", ["ideal", "wire"])
def test_with_drift_and_jitter_every_cell_ticks_when_its_own_clock_says(delivery):
    drift, jitter = 0.01, 0.001
    sc = _scenario("prototype_18_network_ideal", 2.0, drift=drift, jitter=jitter, seed=3)
    sc = sc.model_copy(update={"control": sc.control.model_copy(update={"delivery": delivery}),
                               "sensors": sc.sensors.model_copy(update={"record": True})})
    job = ClockedRun(sc.build())
    result = job.run()
    period, m = sc.control.period, sc.control.clock.slots
    rates = job.clocks.rate
    assert ((rates >= 1 - drift) & (rates <= 1 + drift)).all() and np.ptp(rates) > drift / 2  # drawn per cell
    lateness = []
    for i in range(job.setup.cells.n):
        t = job.tick_times(i)
        k = np.arange(len(t))
        nominal = k * period * rates[i]
        late = t - nominal
        # each tick at its nominal time, late by the jitter and at most one grid instant to be put on the grid
        assert (late >= -1e-9).all() and (late <= jitter + period / m + 1e-9).all(), i
        assert sc.duration - 2 * period < t[-1] < sc.duration  # it ticked to the end
        slope = np.polyfit(k, t, 1)[0]
        assert abs(slope / period - rates[i]) < 1e-3
        lateness.append(late[1:])
    lateness = np.concatenate(lateness)
    assert lateness.max() > 0.8 * jitter and lateness.min() < 0.2 * period / m  # the jitter spreads them
    summary = result.summary()["network"]
    assert summary["sentences_received"] > 0 and summary["clocks"]["cells_a_instant"] < 2
    counts = [len(job.tick_times(i)) for i in range(job.setup.cells.n)]
    assert max(counts) - min(counts) >= 2  # fast clocks tick more often than slow ones
    assert result.parcels[0].trajectory.states[:, 0].max() > result.parcels[0].trajectory.states[0, 0] + 0.05


def test_a_mailbox_keeps_the_latest_sentence_until_its_cell_reads_it():
    schema = Schema.of(v=(1, WordType.U8))
    box = Mailboxes(Mailbox.empty(schema, 2, 1))
    for value in (4, 7):  # a fast neighbour says twice before the cell reads: the later stands
        sent = Mailbox(schema, np.array([[True], [False]]), {"v": np.array([[value], [9]], np.uint8)})
        box.put(sent)
    assert box.mail.present.tolist() == [[True], [False]] and box.mail.values["v"].tolist() == [[7], [0]]
    box.read(np.array([0]))  # read: empty until something new comes
    assert not box.mail.present.any() and box.mail.values["v"].tolist() == [[0], [0]]


def test_an_unsynchronised_run_resumed_half_way_is_the_uninterrupted_run(tmp_path):
    sc = _scenario("merge_two_streams", 1.0, drift=0.01, jitter=0.001, seed=2)
    sc = sc.model_copy(update={"sensors": sc.sensors.model_copy(update={"record": True})})
    plain = run(sc.build())
    job = ClockedRun(sc.build())
    while job.span()[0] < 0.5:
        job.tick()
    job.save(tmp_path / "half.ckpt", 0.3)
    resumed = resume(tmp_path / "half.ckpt")
    _same(plain, resumed)
    for k in ("t", "readings", "wheels", "commands", "sent", "received"):
        assert getattr(plain.cell_log, k).tobytes() == getattr(resumed.cell_log, k).tobytes(), k


@pytest.mark.parametrize("stop, past", [(1.5, False), (1.2, True)])
def test_an_unsynchronised_run_checkpointed_while_it_looks_ahead_is_the_uninterrupted_run(tmp_path, stop, past):
    sc = _scenario("sorting_junction", 3.0, drift=0.01, jitter=0.001, seed=2)
    plain = run(sc.build())
    job = ClockedRun(sc.build())
    while job.span()[0] < stop or job.ahead is None:  # stop where the plant stands behind the cells, looking ahead
        job.tick()
    assert job.plant_t < job.span()[0]
    # the look ahead reaches past the next instant (the cells read from it) or ends before it (taken in there)
    assert (job.ahead.end > job.span()[0]) == past
    job.save(tmp_path / "half.ckpt", 0.3)
    assert job.ahead is None and job.ahead_to is not None  # what a resumed run starts from: none made yet
    job.save(tmp_path / "again.ckpt", 0.3)  # saved again before it looks ahead: it still knows how far
    resumed = resume(tmp_path / "again.ckpt")
    _same(plain, resumed)
    _same(plain, job.run())


def test_a_drifting_run_moves_the_plant_only_where_the_wheels_held_change():
    sc = _scenario("sorting_junction", 4.0, drift=0.01, jitter=0.001, seed=1)
    ahead = run(sc.build())
    # a cell log keeps a row an instant: that run moves the plant to every instant some cell ticks
    logged = run(sc.model_copy(update={"sensors": sc.sensors.model_copy(update={"record": True})}).build())
    a, b = ahead.summary(), logged.summary()
    assert a["network"]["clocks"] == b["network"]["clocks"]  # the same instants, the same ticks
    for key in ("sentences_sent", "sentences_received"):
        assert a["network"][key] == b["network"][key] > 0
    assert sum(p.entered_at is not None for p in ahead.parcels) >= 2
    for p, q in zip(ahead.parcels, logged.parcels):  # the parcels move alike: the plant's calls split elsewhere
        assert p.trajectory.times.tobytes() == q.trajectory.times.tobytes() and p.entered_at == q.entered_at
        np.testing.assert_allclose(p.trajectory.states, q.trajectory.states, rtol=0, atol=1e-6)
    assert a["plant"]["windows"] * 4 < b["plant"]["windows"]


@pytest.mark.parametrize("clock, field", [({"drift": 0.2}, "control.clock.drift"),
                                          ({"jitter": 0.005}, "control"), ({"slots": 0}, "control.clock.slots")])
def test_clocks_that_do_not_fit_the_period_are_refused_with_their_path(clock, field):
    sc, _ = load_scenario("prototype_18_network_ideal")
    data = sc.model_dump(mode="json")
    data["control"]["clock"] = clock
    with pytest.raises(ScenarioError) as err:
        parse_scenario(data)
    assert field in str(err.value)


def test_a_central_controller_keeps_one_clock():
    sc, _ = load_scenario("sorting_junction")
    data = sc.model_dump(mode="json")
    data["control"].update(central=True, clock={"drift": 0.01})
    with pytest.raises(ScenarioError, match="control.clock"):
        parse_scenario(data).build()


def test_the_sorter_delivers_on_unsynchronised_clocks_as_on_a_shared_one():
    sync = sorting_report(run(_scenario("sorting_junction", 12.0).build()))
    own = sorting_report(run(_scenario("sorting_junction", 12.0, drift=0.01, jitter=0.001, seed=0, slots=10).build()))
    assert sync["correct"] >= 2
    assert own["misrouted"] == own["collisions"] == 0
    assert abs(own["correct"] - sync["correct"]) <= 1, (own["correct"], sync["correct"])
