"""A run's state is data: every class that holds part of it writes arrays and plain values (``to_data``) and reads
them back (``from_data`` / ``load_data``) through a checkpoint file to the same object, refusing data of the wrong
shape; a checkpoint's archive holds nothing else (no object of a class named by the file, no setup)."""

import io
import json
import math
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.cells.hardware import MotorParams, WheelDrives
from virtual_vehicle.cells.network.delivery import IdealRounds
from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import ChangedCells, Flood
from virtual_vehicle.cells.network.sentence import WordType
from virtual_vehicle.cells.network.topology import Topology, from_layout
from virtual_vehicle.cells.network.wire import WireLevel, WireParams
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.engine.plant import Integration, Plant, PlantRecord
from virtual_vehicle.engine.stepping import Event, Trajectory
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import rectangle
from virtual_vehicle.physics.collide import ContactParams
from virtual_vehicle.physics.laws import LAWS
from virtual_vehicle.run import checkpoint
from virtual_vehicle.run.sim import FieldRun, LatencyStats, NetworkRun

PLAIN_TAGS = {"float", "np", "array", "rows", "list", "tuple", "dict", "set", "frozenset", "deque", "bytes", "ref"}
"""The tree codec's tags for plain values: nothing else may appear in a checkpoint."""


def through_file(tree):
    """``tree`` written into a checkpoint file's archive and read back."""
    doc, arrays = checkpoint.encode(tree)
    back, arrays = checkpoint.unpack(checkpoint.pack({"format_version": checkpoint.FORMAT_VERSION, "state": doc},
                                                     arrays))
    return checkpoint.decode(back["state"], arrays)


def same_data(a, b, where="data"):
    """Assert that two data trees are the same: keys, lengths, types, and every array's dtype, shape and bits."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} vs {type(b).__name__}"
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            same_data(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b)):
            same_data(x, y, f"{where}[{k}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), where
    elif isinstance(a, float):
        assert a == b or (math.isnan(a) and math.isnan(b)), where
    else:
        assert a == b, where


def tags_and_dtypes(node, tags: set):
    """Every ``$`` tag of a checkpoint document's tree, gathered into ``tags``."""
    if isinstance(node, dict):
        if "$" in node:
            tags.add(node["$"])
        for v in node.values():
            tags_and_dtypes(v, tags)
    elif isinstance(node, list):
        for v in node:
            tags_and_dtypes(v, tags)
    return tags


# --------------------------------------------------------------------------- each class's data form

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
ids = st.tuples() | st.lists(st.integers(0, 10**6), max_size=4).map(tuple)
events = st.lists(st.builds(
    Event, t=finite, kind=st.sampled_from(["support", "tip", "contact", "release"]),
    state=st.tuples(*[finite] * 6), entered=ids, left=ids, lifted=ids, touched=ids,
    message=st.text(max_size=20), partner=st.text(max_size=8)), max_size=6)


@st.composite
def trajectories(draw):
    k = draw(st.integers(0, 5))
    times = np.array(draw(st.lists(finite, min_size=k, max_size=k)), dtype=float)
    states = np.array(draw(st.lists(finite, min_size=6 * k, max_size=6 * k)), dtype=float).reshape(k, 6)
    stats = draw(st.dictionaries(st.text(max_size=10), st.integers(-2**62, 2**62) | finite | st.booleans(),
                                 max_size=4))
    return Trajectory(times, states, draw(events), draw(st.sampled_from(["completed", "tipped", "left"])),
                      draw(finite), draw(st.integers(0, 10**9)), draw(st.integers(0, 10**9)), stats)


@settings(max_examples=40, deadline=None)
@given(events)
def test_events_are_columns_that_read_back_to_the_same_events(evs):
    cols = Event.to_columns(evs)
    for key, v in cols.items():  # arrays, ragged int columns, or lists of strings
        assert (isinstance(v, np.ndarray) or (isinstance(v, dict) and all(isinstance(x, np.ndarray) for x in
                                                                          v.values()))
                or all(type(x) is str for x in v)), key
    back = Event.from_columns(through_file(cols))
    assert back == evs and all(type(b.t) is float and type(b.message) is str for b in back)


@settings(max_examples=40, deadline=None)
@given(trajectories())
def test_a_trajectory_reads_back_to_the_same_bits(tr):
    back = Trajectory.from_data(through_file(tr.to_data()))
    assert back.times.tobytes() == tr.times.tobytes() and back.states.tobytes() == tr.states.tobytes()
    assert (back.events, back.status, back.t_end, back.segments, back.rhs_evals, back.stats) == (
        tr.events, tr.status, tr.t_end, tr.segments, tr.rhs_evals, tr.stats)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 2**40), min_size=7, max_size=7), finite, st.lists(st.integers(0, 99), max_size=5))
def test_a_plant_record_reads_back_the_same(counts, depth, per_parcel):
    rec = PlantRecord(*counts[:1], depth, *counts[1:6], contacts_per_parcel=per_parcel)
    assert PlantRecord.from_data(through_file(rec.to_data())) == rec


@settings(max_examples=30, deadline=None)
@given(st.lists(st.lists(st.floats(1e-7, 1e4), max_size=6), max_size=4))
def test_latency_statistics_read_back_the_same(batches):
    lat = LatencyStats()
    for b in batches:
        lat.add(np.array(b))
    back = LatencyStats.from_data(through_file(lat.to_data()))
    assert back == lat and back.percentile(95) == lat.percentile(95)


SCHEMA = Schema.of(a=(1, WordType.U8), b=(2, WordType.I16), c=(3, WordType.F32), d=(4, WordType.BOOL))


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 6), st.integers(1, 4), st.integers(0, 2**32 - 1))
def test_a_mailbox_reads_back_the_same_sentences(n, ports, seed):
    rng = np.random.default_rng(seed)
    box = Mailbox(SCHEMA, rng.random((n, ports)) < 0.5,
                  {"a": rng.integers(0, 255, (n, ports), dtype=np.uint8),
                   "b": rng.integers(-999, 999, (n, ports)).astype(np.int16),
                   "c": rng.normal(size=(n, ports)).astype(np.float32), "d": rng.random((n, ports)) < 0.5})
    back = Mailbox.from_data(through_file(box.to_data()), SCHEMA)
    assert back.schema == SCHEMA and all(x.dtype == y.dtype and np.array_equal(x, y)
                                         for x, y in zip(back.arrays, box.arrays))


@settings(max_examples=20, deadline=None)
@given(st.integers(2, 5), st.integers(1, 4), st.lists(st.integers(0, 19), max_size=3))
def test_a_topology_reads_back_the_same_links(nx, ny, dead):
    topo = from_layout(layout.grid(nx, ny, 0.1)).with_faults(dead_cells=[d for d in dead if d < nx * ny])
    back = Topology.from_data(through_file(topo.to_data()))
    same_data(back.to_data(), topo.to_data())
    assert np.array_equal(back.connected, topo.connected)


@settings(max_examples=20, deadline=None)
@given(st.integers(1, 5), st.integers(0, 2**32 - 1))
def test_wheel_drives_read_back_and_go_on_to_the_same_bits(n, seed):
    rng = np.random.default_rng(seed)
    drives = WheelDrives(n, MotorParams())
    for _ in range(3):
        drives.step(rng.normal(0, 0.3, (n, 2)), rng.normal(0, 1, (n, 2)), 0.01)
    back = WheelDrives.from_data(through_file(drives.to_data()), drives.p)
    command, load = rng.normal(0, 0.3, (n, 2)), rng.normal(0, 1, (n, 2))
    assert drives.step(command, load, 0.01).tobytes() == back.step(command, load, 0.01).tobytes()
    same_data(back.to_data(), drives.to_data())


@pytest.mark.parametrize("law", ["coulomb", "stick_slip"])
def test_a_plant_read_back_mid_contact_goes_on_to_the_same_bits(law):
    """Two boxes pushing each other (contact pairs, warm-started impulses) or a parcel on fixed-step stick-slip
    wheels (each wheel's memory; the event-driven law keeps none): a plant made afresh and given the state data moves
    the parcels as the one that wrote it."""
    specs = [rectangle(0.3, 0.3, 1.0, 0.5, name="a"), rectangle(0.3, 0.3, 1.0, 0.5, name="b")]
    cells = layout.grid(40, 20, 0.05)

    def make():
        mode = "event" if law == "coulomb" else "fixed"
        return Plant(cells, specs, LAWS[law], 9.81, Integration(mode=mode, dt=1e-3), ContactParams(mu=0.3))

    wheels = np.zeros((cells.n, 2)) if law == "coulomb" else np.tile([0.2, 0.0], (cells.n, 1))
    ys = [np.array([0.4, 0.5, 0, 0.4, 0, 0]), np.array([1.0, 0.5, 0, 0, 0, 0])]
    a = make()
    a.advance(ys, [True, True], wheels, 0.0, 1.0, 0.01)
    data = a.state()
    if law == "coulomb":
        assert len(data["touching"]) and len(data["warm"]["pairs"]) and data["record"]["parcel_contacts"] == 1
    else:
        assert all(len(m["keys"]) for m in data["memory"])
    b = make()
    b.restore(through_file(data))
    same_data(b.state(), data)
    ys_b = [y.copy() for y in ys]
    ta = a.advance(ys, [True, True], wheels, 1.0, 1.5, 0.01)
    tb = b.advance(ys_b, [True, True], wheels, 1.0, 1.5, 0.01)
    for p, q in zip(ta, tb):
        assert p.states.tobytes() == q.states.tobytes() and p.events == q.events
    same_data(b.state(), a.state())


def _outboxes(n, ports, ticks, seed):
    rng = np.random.default_rng(seed)
    return [Mailbox(SCHEMA, rng.random((n, ports)) < 0.4,
                    {"a": rng.integers(0, 255, (n, ports), dtype=np.uint8),
                     "b": rng.integers(-999, 999, (n, ports)).astype(np.int16),
                     "c": rng.normal(size=(n, ports)).astype(np.float32), "d": rng.random((n, ports)) < 0.5})
            for _ in range(ticks)]


@pytest.mark.parametrize("model", ["wire", "ideal rounds"])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_delivery_model_read_back_carries_on_to_the_same_bits(model, seed):
    """Sentences queued and in flight, events pending, random draws: the delivery made afresh and loaded with the
    data delivers what the one that wrote it delivers, tick after tick."""
    topo = from_layout(layout.grid(4, 3, 0.1)).with_faults(dead_links=[(0, 0)])
    if model == "wire":
        def make():
            return WireLevel(topo, WireParams(bit_error_rate=2e-3, loss_rate=0.05, backoff_max=2e-3), seed=seed)
    else:
        def make():
            return IdealRounds(topo, loss_rate=0.2, seed=seed)
    period = 0.004  # shorter than one sentence on the wire at 9600 baud: queues and transfers carry over
    boxes = _outboxes(topo.n, topo.ports, 12, seed)
    a = make()
    inbox = None
    for k, box in enumerate(boxes[:6]):
        inbox, _ = a.exchange(box, k * period, period)
    data = a.to_data()
    if model == "wire":
        assert len(data["sentences"]["cell"]) and len(data["events"]["t"])  # something is carried over
    b = make()
    b.load_data(through_file(data), Mailbox.from_data(through_file(inbox.to_data()), SCHEMA))
    same_data(b.to_data(), data)
    for k, box in enumerate(boxes[6:], start=6):
        (ia, sa), (ib, sb) = a.exchange(box, k * period, period), b.exchange(box, k * period, period)
        assert all(x.tobytes() == y.tobytes() for x, y in zip(ia.arrays, ib.arrays))
        for key in ("sent", "received", "bytes_sent", "bytes_received", "latencies"):
            assert getattr(sa, key).tobytes() == getattr(sb, key).tobytes(), key
        assert (sa.lost, sa.corrupted, sa.undetected, sa.dropped, sa.extra) == (
            sb.lost, sb.corrupted, sb.undetected, sb.dropped, sb.extra)


class _Stationary(Flood):
    stationary = True

    def __init__(self):
        super().__init__(3)


def test_a_changed_cells_stepper_keeps_its_schedule_and_counts_not_its_cache():
    stepper = ChangedCells(_Stationary())
    stepper.backoff, stepper.skip, stepper.ticks, stepper.stepped = 8, 3, 40, 900
    stepper.last = {"state": {}}
    data = through_file(stepper.to_data())
    assert data == {"backoff": 8, "skip": 3, "ticks": 40, "stepped": 900}
    fresh = ChangedCells(_Stationary())
    fresh.load_data(data)
    assert (fresh.backoff, fresh.skip, fresh.ticks, fresh.stepped, fresh.last) == (8, 3, 40, 900, None)


@pytest.mark.parametrize("reader, bad, message", [
    (lambda d: Trajectory.from_data(d), lambda d: d.update(times=d["times"].astype(np.float32)), "float32"),
    (lambda d: Trajectory.from_data(d), lambda d: d.update(states=np.zeros((9, 6))), "shape"),
    (lambda d: Trajectory.from_data(d), lambda d: d.pop("stats"), "keys"),
    (lambda d: Trajectory.from_data(d), lambda d: d["events"]["entered"].update(counts=np.array([5])), "add up"),
    (lambda d: Trajectory.from_data(d), lambda d: d.update(segments=-1), "segments"),
    (lambda d: Trajectory.from_data(d), lambda d: d.update(stats={"x": "text"}), "stats"),
])
def test_data_of_the_wrong_shape_or_kind_is_refused_with_a_value_error(reader, bad, message):
    tr = Trajectory(np.zeros(2), np.zeros((2, 6)), [Event(0.5, "tip", (0.0,) * 6, (3,))], "tipped", 0.5, 1, 2, {})
    d = through_file(tr.to_data())
    bad(d)
    with pytest.raises(ValueError, match=message):
        reader(d)


@pytest.mark.parametrize("reader, data, message", [
    (lambda d: LatencyStats.from_data(d), {"count": 1, "total": 0.0, "min": 0.0, "max": 0.0,
                                           "counts": np.zeros(512, dtype=np.int64)}, "add up"),
    (lambda d: Topology.from_data(d), {"neighbor": np.full((2, 4), 7), "back_port": np.zeros((2, 4), dtype=np.int64),
                                       "link_up": np.ones((2, 4), bool), "alive": np.ones(2, bool)}, "out of range"),
    (lambda d: Mailbox.from_data(d, SCHEMA), {"present": np.zeros((2, 4), bool), "values": {}}, "keys"),
    (lambda d: WheelDrives.from_data(d), {k: np.zeros((3, 2)) for k in ("speed", "angle", "counts", "integral",
                                                                        "measured", "voltage")}, "counts"),
    (lambda d: ChangedCells(_Stationary()).load_data(d), {"backoff": 0, "skip": 0, "ticks": 0, "stepped": 0},
     "backoff"),
    (lambda d: IdealRounds(from_layout(layout.grid(2, 2, 0.1))).load_data(d),
     {"rng": {"bit_generator": "os.system", "state": {}}}, "unknown bit generator"),
])
def test_each_class_refuses_data_that_is_not_its_own(reader, data, message):
    with pytest.raises(ValueError, match=message):
        reader(data)


# --------------------------------------------------------------------------- runs: state declared, data only

def _network(name, duration, **update):
    sc = load_scenario(name)[0]
    return sc.model_copy(update={"duration": duration, **update})


def _cases():
    ideal = _network("prototype_18_network_ideal", 1.0)
    merge = _network("merge_two_streams", 1.5)
    return {
        "wire": lambda: NetworkRun(_network("prototype_18_network", 1.0).build()),
        "ideal rounds, motors, recorded": lambda: NetworkRun(ideal.model_copy(update={
            "wheels": ideal.wheels.model_copy(update={"model": "motor"}),
            "sensors": ideal.sensors.model_copy(update={"record": True})}).build()),
        "central sorter": lambda: NetworkRun(merge.model_copy(update={
            "control": merge.control.model_copy(update={"central": True})}).build()),
        "changed cells": lambda: NetworkRun(_network("sorting_junction", 2.0).build()),
        "constant field": lambda: FieldRun(_network("crossing_30x30", 0.6).build()),
        "stick-slip field": lambda: FieldRun(_network("stick_slip_pickup", 0.4).build()),
    }


CASES = _cases()


def _half_way(job):
    if isinstance(job, FieldRun):
        job.step(job.setup.scenario.duration / 2, None)
    else:
        while job.k < job.ticks // 2:
            job.tick()
    return job


@pytest.mark.parametrize("case", list(CASES))
def test_a_checkpoint_holds_the_declared_state_as_plain_data_and_reads_back_to_it(tmp_path, case):
    job = _half_way(CASES[case]())
    if case == "changed cells":
        assert job.stepper is not None
    data = job.checkpoint_bytes(0.25)
    with zipfile.ZipFile(io.BytesIO(data.partition(b"\n")[2])) as z:
        doc = json.loads(z.read("checkpoint.json"))
        for name in z.namelist()[1:]:
            with z.open(name) as f:
                assert np.lib.format.read_array(f, allow_pickle=False).dtype.kind in "biufU", name
    tags = tags_and_dtypes(doc["state"], set())
    assert tags <= PLAIN_TAGS, tags - PLAIN_TAGS  # no objects of classes, no parts of the setup, no generators
    state = checkpoint.decode(doc["state"], checkpoint.unpack(data)[1])
    assert sorted(state) == sorted(job.STATE)
    # what is read back is what was written: a run made afresh from the setup and loaded writes the same data
    job.save(tmp_path / "c.ckpt", 0.25)  # goes on from what it read back
    again, arrays = checkpoint.unpack(job.checkpoint_bytes(0.25))
    first, arrays0 = checkpoint.unpack(data)
    same_data(checkpoint.decode(again["state"], arrays), checkpoint.decode(first["state"], arrays0))
    assert again["position"] == first["position"]
