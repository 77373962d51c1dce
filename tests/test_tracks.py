"""What a long ticked run keeps: each parcel's events as columns (:class:`~virtual_vehicle.run.tracks.EventLog`: the
same events read back, the same data written, a fraction of the memory), and nothing of a parcel that left."""

from __future__ import annotations

import tracemalloc

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from virtual_vehicle.engine.stepping import Event
from virtual_vehicle.run.tracks import EventLog, ParcelTrack

_floats = st.floats(allow_nan=False, allow_infinity=False, width=64)
_cells = st.lists(st.integers(0, 10**6), max_size=5).map(tuple)
_events = st.builds(Event, _floats, st.sampled_from(["support", "tip", "contact", "release", "stick", "slip",
                                                     "a kind no law has yet"]),
                    st.tuples(*[_floats] * 6), _cells, _cells, _cells, _cells, st.text(max_size=8),
                    st.text(max_size=8))


@given(st.lists(_events, max_size=12))
def test_an_event_log_reads_back_the_events_it_took(events):
    log = EventLog(events)
    assert len(log) == len(events)
    assert list(log) == events and log == events and events == log
    assert all(log[k] == e for k, e in enumerate(events))
    if events:
        assert log[-1] == events[-1] and log[1:] == events[1:]
    cols, want = log.to_columns(), Event.to_columns(events)
    assert cols.keys() == want.keys()
    for name, value in want.items():
        if isinstance(value, dict):
            for part in ("counts", "flat"):
                assert np.array_equal(cols[name][part], value[part]) and cols[name][part].dtype == np.int64
        elif isinstance(value, np.ndarray):
            assert np.array_equal(cols[name], value) and cols[name].shape == value.shape
        else:
            assert cols[name] == value
    assert EventLog.from_columns(cols) == events


def test_an_event_log_settles_support_events_made_lazily():
    """An event made by Event.support_between keeps the two pieces' keys until read: the log works its changed
    cells out when it takes the event in (lifted: in contact before, still under it, not in contact after)."""
    ev = Event.support_between(0.5, (1.0, 2.0, 0.0, 0.1, 0.0, 0.0), ((1, 2, 3), (1, 2, 3)), ((2, 3, 4), (2, 4)))
    log = EventLog([ev])
    got = log[0]
    assert (got.entered, got.left, got.lifted, got.touched) == ((4,), (1,), (3,), ())
    assert got == ev


def test_an_event_log_refuses_what_is_not_an_event():
    log = EventLog()
    try:
        log.append(Event(0.0, "support", (0.0,) * 5))
    except ValueError as exc:
        assert "6 numbers" in str(exc)
    else:
        raise AssertionError("a state of 5 numbers was taken")
    assert len(log) == 0
    try:
        log[0]
    except IndexError:
        pass
    else:
        raise AssertionError("an empty log gave an event")


def test_an_event_log_holds_a_run_of_events_in_a_fraction_of_their_memory():
    """2,000 support events as a run makes them (a changed cell or two each, a state of six floats): the log takes
    less than a fifth of the memory the event objects do (measured: ~100 against ~670 bytes an event)."""
    def made():
        rng = np.random.default_rng(0)
        return [Event.support(float(t), tuple(rng.normal(size=6).tolist()), (int(rng.integers(10**4)),), (),
                              (), ()) for t in range(2000)]

    def traced(build):
        tracemalloc.start()
        try:
            kept = build()
            size = tracemalloc.get_traced_memory()[0]
        finally:
            tracemalloc.stop()
        return size, kept

    as_objects, events = traced(made)
    as_log, log = traced(lambda: EventLog(events))  # (the log's own memory: the events exist already)
    assert log == events
    assert as_log < 0.2 * as_objects, (as_log, as_objects)


def test_a_track_writes_and_reads_its_events_as_columns():
    track = ParcelTrack()
    track.events.extend([Event(0.1, "support", (0.0,) * 6, (1, 2), (), (), ()),
                         Event(0.2, "stick", (1.0,) * 6, message="3:0 4:1")])
    cols = track.events.to_columns()
    again = EventLog.from_columns(cols)
    assert again == track.events and type(again) is EventLog


def test_a_delivered_parcels_tables_are_freed_at_once():
    """A parcel that left the array lets go of its compiled loop's table (~0.8 MB on the junction): its model and
    the table referred to each other, so they waited for a full garbage collection, which a long run makes rarer as
    its results grow (on the hour's junction ~40 of them waited at a time). With the collector off, the tables alive
    at the end are those of the parcels still on the array."""
    import gc

    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.engine.dynamics import _PieceTable
    from virtual_vehicle.run.sim import run_network

    sc, _ = load_scenario("sorting_junction")
    run_network(sc.model_copy(update={"duration": 1.0}).build())  # (what compiles, compiles here: not counted)
    setup = sc.model_copy(update={"duration": 14.0}).build()

    def all_tables():  # (type(), not isinstance: a dead weak proxy elsewhere in the process raises on isinstance)
        return [o for o in gc.get_objects() if type(o) is _PieceTable]

    gc.collect()
    before = {id(t) for t in all_tables()}  # other tests' tables that something still holds: not this run's
    gc.disable()
    try:
        res = run_network(setup)
        report = res.summary()["sorting"]
        tables = [t for t in all_tables() if id(t) not in before]
        live = [t for t in tables if t.owner is not None]
    finally:
        gc.enable()
    assert report["correct"] >= 1  # a parcel left the array
    assert len(tables) == len(live) <= report["on_array"], (len(tables), len(live), report["on_array"])
