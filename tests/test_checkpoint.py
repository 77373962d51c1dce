"""Checkpoints are data: the tree codec, files that must not run code, version checks, and runs resumed bit for bit."""

import dataclasses
import io
import json
import os
import pickle
import zipfile
from collections import deque

import numpy as np
import pytest

from virtual_vehicle import __version__
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.errors import VirtualVehicleError
from virtual_vehicle.run import checkpoint
from virtual_vehicle.run.checkpoint import CheckpointError, decode, encode


@dataclasses.dataclass
class _Point:
    x: float


def _roundtrip(tree):
    doc, arrays = encode(tree)
    data = checkpoint.pack({"format_version": checkpoint.FORMAT_VERSION, "state": doc}, arrays)
    doc2, arrays2 = checkpoint.unpack(data)
    return decode(doc2["state"], arrays2)


def test_the_codec_gives_back_every_value_with_its_type_and_bits():
    shared = np.arange(6.0).reshape(2, 3)
    ro = np.array([1, 2], dtype=np.int16)
    ro.setflags(write=False)
    tree = {
        "floats": [0.1, -0.0, float("inf"), float("-inf"), 1e-310, 2 ** 0.5],
        "nan": float("nan"),
        "ints": [0, -7, 2 ** 100, True, None, "text"],
        "np": [np.int64(-3), np.float64(0.1), np.float32(np.nan), np.bool_(True), np.uint8(255)],
        (1, 2, 3): {frozenset({1, 2}): {(4, 5), (6, 7)}},
        "queue": deque([1, (2.5, "x")], maxlen=5),
        "arrays": [shared, shared, ro, np.zeros((0, 6)), np.array(3.25), np.array(["contact", ""])],
        "rows": [np.ones(6), np.full(6, 2.0), np.zeros(6)],
        "bytes": b"\x00\xffbytes",
    }
    back = _roundtrip(tree)
    assert back["floats"] == tree["floats"] and np.signbit(back["floats"][1]) and np.isnan(back["nan"])
    assert back["ints"] == tree["ints"] and type(back["ints"][3]) is bool and type(back["ints"][0]) is int
    for a, b in zip(back["np"][:2] + back["np"][3:], tree["np"][:2] + tree["np"][3:]):
        assert type(a) is type(b) and a == b
    assert type(back["np"][2]) is np.float32 and np.isnan(back["np"][2])
    assert back[(1, 2, 3)] == {frozenset({1, 2}): {(4, 5), (6, 7)}}
    assert type(back["queue"]) is deque and back["queue"].maxlen == 5 and list(back["queue"]) == [1, (2.5, "x")]
    a, b, c, d, e, f = back["arrays"]
    assert a is b and np.array_equal(a, shared) and a.flags.writeable  # shared stays shared
    assert not c.flags.writeable and c.dtype == np.int16 and d.shape == (0, 6) and e.shape == () and e == 3.25
    assert f.tolist() == ["contact", ""]
    assert [r.tolist() for r in back["rows"]] == [r.tolist() for r in tree["rows"]]
    assert back["bytes"] == tree["bytes"]


def test_the_codec_refuses_what_is_not_plain_data():
    for bad in (object(), lambda: 0, np.array([None], dtype=object), 1 + 2j, np.complex128(1j), _Point(1.0),
                np.random.default_rng(0), np.array(["2020-01-01"], dtype="datetime64[D]")):
        with pytest.raises(TypeError):
            encode({"x": bad})
    with pytest.raises(TypeError, match=r"state\['x'\]\[1\]: a builtins"):
        encode({"x": [1, print]})


@pytest.mark.parametrize("node, message", [
    ({"$": "obj", "@": 0, "class": "_Point", "fields": []}, "unknown node 'obj'"),
    ({"$": "ext", "name": "setup"}, "unknown node 'ext'"),
    ({"$": "rng", "bit_generator": "PCG64", "state": {}}, "unknown node 'rng'"),
    ({"$": "np", "dtype": "O", "v": 1}, "dtype"),
    ({"$": "ref", "@": 3}, "unknown object"),
    ({"$": "array", "k": 7}, "no array"),
    ({"$": "eval", "v": "__import__('os')"}, "unknown node"),
    ([1, 2], "untagged"),
])
def test_the_decoder_makes_nothing_it_does_not_know(node, message):
    with pytest.raises(CheckpointError, match=message):
        decode(node, [])


# --------------------------------------------------------------------------- checkpoint files


def _network(name="prototype_18_network", duration=1.0, **update):
    sc = load_scenario(name)[0]
    return sc.model_copy(update={"duration": duration, **update})


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A real checkpoint of a short networked run (taken half way) and the run's uninterrupted result."""
    from virtual_vehicle.run.sim import NetworkRun

    path = tmp_path_factory.mktemp("ck") / "run.ckpt"
    job = NetworkRun(_network().build())
    while job.k < job.ticks // 2:
        job.tick()
    job.save(path, 0.25)
    return path


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _rewritten(good, tmp_path, document=None, members=()):
    """``good``'s checkpoint with its document changed by ``document`` and extra or replaced zip ``members``."""
    data = good.read_bytes()
    header, _, rest = data.partition(b"\n")
    out = io.BytesIO()
    members = dict(members)
    with zipfile.ZipFile(io.BytesIO(rest)) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            body = src.read(info)
            if info.filename == "checkpoint.json" and document is not None:
                doc = json.loads(body)
                document(doc)
                body = json.dumps(doc).encode()
            dst.writestr(info.filename, members.pop(info.filename, body))
        for name, body in members.items():
            dst.writestr(name, body)
    path = tmp_path / "crafted.ckpt"
    path.write_bytes(header + b"\n" + out.getvalue())
    return path


def _object_npy(marker) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.array([_Evil(marker)], dtype=object), allow_pickle=True)
    return buf.getvalue()


def test_a_checkpoint_holds_only_json_and_plain_arrays(good):
    with zipfile.ZipFile(io.BytesIO(good.read_bytes().partition(b"\n")[2])) as z:
        names = z.namelist()
        doc = json.loads(z.read("checkpoint.json"))
        assert names[0] == "checkpoint.json" and all(n.startswith("arrays/") and n.endswith(".npy")
                                                     for n in names[1:])
        for n in names[1:]:
            with z.open(n) as f:
                assert not np.lib.format.read_array(f, allow_pickle=False).dtype.hasobject
    assert doc["format_version"] == checkpoint.FORMAT_VERSION and doc["package_version"] == __version__
    assert doc["kind"] == "network" and doc["scenario"]["name"] == "prototype_18_network"


@pytest.mark.parametrize("craft", ["old pickle format", "pickle after the header", "pickled array",
                                   "class named by the file", "not a zip"])
def test_a_crafted_checkpoint_runs_nothing_and_says_why(good, tmp_path, craft):
    from virtual_vehicle.run.sim import resume

    marker = tmp_path / "ran"
    evil = pickle.dumps(_Evil(marker))
    if craft == "old pickle format":
        path = tmp_path / "old.ckpt"
        path.write_bytes(b"virtual_vehicle checkpoint 1\n" + evil)
        message = "format '1'.*never loaded"
    elif craft == "pickle after the header":
        path = tmp_path / "x.ckpt"
        path.write_bytes(checkpoint.HEADER + evil)
        message = "damaged"
    elif craft == "pickled array":
        path = _rewritten(good, tmp_path, members={"arrays/0.npy": _object_npy(marker)})
        message = "arrays/0.npy: an array of Python objects"
    elif craft == "class named by the file":
        def document(doc):
            doc["state"]["items"][0][1] = {"$": "obj", "@": 99999, "class": "_Evil", "fields": []}
        path = _rewritten(good, tmp_path, document)
        message = "unknown node 'obj'"
    else:
        path = tmp_path / "x.ckpt"
        path.write_bytes(checkpoint.HEADER + b"PK\x03\x04 junk")
        message = "damaged"
    with pytest.raises(VirtualVehicleError, match=message):
        resume(path)
    assert not marker.exists()


def _set_state(doc, key, node):
    (pair,) = [p for p in doc["state"]["items"] if p[0] == key]
    pair[1] = node


@pytest.mark.parametrize("change, message", [
    (lambda doc: doc.update(package_version="0.0.1"), "written by virtual_vehicle 0.0.1; this is " + __version__),
    (lambda doc: doc.update(format_version=5), "format 5"),
    (lambda doc: doc.update(kind="movie"), "run kind"),
    (lambda doc: doc.update(kind="field"), "a field run's checkpoint whose scenario is not one"),
    (lambda doc: doc["scenario"].update(duration=-1.0), "its scenario: duration"),
    (lambda doc: doc["position"].update(next_fault=4), "does not fit its scenario"),
    (lambda doc: doc["scenario"]["array"].update(nx=7), "builds another setup"),
    (lambda doc: _set_state(doc, "per_cell", {"$": "dict", "items": []}), "does not fit its scenario.*per_cell"),
    (lambda doc: _set_state(doc, "k", "many"), "does not fit its scenario"),
    (lambda doc: _set_state(doc, "k", 10**6), "ticks done of the run's"),
    (lambda doc: _set_state(doc, "tracks", {"$": "list", "items": []}), "not one track per parcel"),
    (lambda doc: _set_state(doc, "ys", {"$": "array", "k": 1}), "state.ys: a bool array"),  # (array 1: active)
])
def test_a_checkpoint_of_another_version_or_scenario_is_refused_with_one_message(good, tmp_path, change, message):
    from virtual_vehicle.run.sim import resume

    with pytest.raises(VirtualVehicleError, match=message):
        resume(_rewritten(good, tmp_path, change))


def test_a_run_whose_setup_was_changed_after_it_was_built_is_not_resumed_from_its_scenario(tmp_path):
    from virtual_vehicle.run.sim import NetworkRun, resume

    setup = _network().build()
    setup.states[0] = setup.states[0] + [0.01, 0, 0, 0, 0, 0]  # not what its scenario says
    job = NetworkRun(setup)
    job.tick()
    job.save(tmp_path / "c.ckpt", 0.5)
    with pytest.raises(VirtualVehicleError, match="builds another setup"):
        resume(tmp_path / "c.ckpt")


@pytest.mark.parametrize("version, message", [("5", "format '5'; this version reads format 4"),
                                              ("2", "format '2'.*not its state as data.*run the scenario again")])
def test_another_format_version_in_the_header_is_refused(tmp_path, version, message):
    from virtual_vehicle.run.sim import resume

    path = tmp_path / "other.ckpt"
    path.write_bytes(b"virtual_vehicle checkpoint " + version.encode() + b"\n" + b"anything")
    with pytest.raises(VirtualVehicleError, match=message):
        resume(path)


def test_the_cli_resume_of_a_bad_file_exits_2_with_one_message(good, tmp_path):
    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app

    marker = tmp_path / "ran"
    bad = _rewritten(good, tmp_path, members={"arrays/0.npy": _object_npy(marker)})
    res = CliRunner().invoke(app, ["resume", str(bad)])
    assert res.exit_code == 2 and not marker.exists()
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "cannot resume" in lines[0] and "Traceback" not in res.output


# --------------------------------------------------------------------------- bit for bit


def _same(a, b, work=True):
    """The same run to the last bit; ``work``: and the same count of support problems solved (a resumed run solves
    again what the caches it does not inherit held, and moves the same)."""
    for p, q in zip(a.parcels, b.parcels):
        assert p.trajectory.times.tobytes() == q.trajectory.times.tobytes()
        assert p.trajectory.states.tobytes() == q.trajectory.states.tobytes()
        sp, sq = dict(p.trajectory.stats), dict(q.trajectory.stats)
        if not work:
            sp.pop("solves", None), sq.pop("solves", None)
        assert p.trajectory.events == q.trajectory.events and sp == sq
        assert (p.trajectory.status, p.entered_at) == (q.trajectory.status, q.entered_at)
    sa, sb = a.summary(), b.summary()
    for s in (sa, sb):
        s.pop("wall_time_s"), s.pop("real_time_factor")
    assert sa == sb
    if a.network is not None:
        for k, v in a.network.per_tick.items():
            assert v.tobytes() == b.network.per_tick[k].tobytes(), k
        assert a.network.latency == b.network.latency


@pytest.mark.parametrize("case", ["wire", "ideal rounds, motors, recorded", "central sorter", "hexagonal sorter"])
def test_a_networked_run_resumed_half_way_is_the_uninterrupted_run(tmp_path, case):
    from virtual_vehicle.run.sim import NetworkRun, resume, run

    if case == "wire":
        sc = _network()
    elif case.startswith("hexagonal"):  # six ports a cell, omni wheels: a parcel turning out of the entry
        sc = _network("hex_sorting_junction", 2.5)
    elif case.startswith("central"):
        base = _network("merge_two_streams", 1.5)
        sc = base.model_copy(update={"control": base.control.model_copy(update={"central": True})})
    else:
        base = _network("prototype_18_network_ideal")
        sc = base.model_copy(update={"wheels": base.wheels.model_copy(update={"model": "motor"}),
                                     "sensors": base.sensors.model_copy(update={"record": True})})
    plain = run(sc.build())
    job = NetworkRun(sc.build())
    while job.k < job.ticks // 2:
        job.tick()
    job.save(tmp_path / "half.ckpt", 0.3)
    resumed = resume(tmp_path / "half.ckpt")  # and checkpointing again every 0.3 s on the way
    _same(plain, resumed, work=False)
    if resumed.cell_log is not None:
        for k in ("t", "readings", "wheels", "commands", "sent", "received"):
            assert getattr(plain.cell_log, k).tobytes() == getattr(resumed.cell_log, k).tobytes(), k
    checkpointed = run(sc.build(), checkpoint=tmp_path / "c.ckpt", checkpoint_every=0.3)
    _same(plain, checkpointed, work=False)
    _same(checkpointed, resume(tmp_path / "c.ckpt"))


def _npy_header_only(shape) -> bytes:
    """A .npy file whose header claims ``shape`` float64 values and that holds none of them."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buf.getvalue()


@pytest.mark.parametrize("claim", ["a header claiming 10^13 values", "a stack of 10^9 empty rows",
                                   "more than may unpack"])
def test_a_checkpoint_that_claims_huge_arrays_is_refused_before_allocating(good, tmp_path, monkeypatch, claim):
    from virtual_vehicle.run.sim import resume

    if claim == "a header claiming 10^13 values":
        path = _rewritten(good, tmp_path, members={"arrays/0.npy": _npy_header_only((10**13,))})
        message = "does not fit its"
    elif claim == "a stack of 10^9 empty rows":
        path = _rewritten(good, tmp_path, document=lambda d: _set_state(d, "ys", {"$": "rows", "k": 0}),
                          members={"arrays/0.npy": _npy_header_only((10**9, 0))})
        message = "rows of an array of shape"
    else:
        monkeypatch.setattr(checkpoint, "MAX_BYTES", 1000)
        path = good
        message = "more than the 1000"
    with pytest.raises(VirtualVehicleError, match=message):
        resume(path)


def test_an_infinite_checkpoint_interval_is_refused(tmp_path):
    from virtual_vehicle.run.sim import run

    with pytest.raises(VirtualVehicleError, match="checkpoint_every: must be a positive, finite"):
        run(_network(duration=0.1).build(), checkpoint=tmp_path / "c.ckpt", checkpoint_every=float("inf"))
