"""Invariants of the whole simulator: rigid motions of the scene move the result with it, cell numbering does not
matter, runs are bit-reproducible, interrupted writes leave no complete-looking file."""

import json
import os

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from virtual_vehicle.config.scenario import bundled_scenarios, load_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.run import files, io
from virtual_vehicle.run.sim import run

LAWS = {"coulomb": laws.CoulombLaw(), "viscous": laws.ViscousLaw(), "stick_slip": laws.StickSlipLaw()}


def rot(a):
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def simulate(cells, spec, velocities, law, y0, T=0.6):
    m = ParcelModel(cells, spec, velocities, law)
    return integrate(m, y0, 0.0, T, dt=1e-3, sample_dt=0.05)


@settings(max_examples=12, deadline=None)
@given(st.sampled_from(sorted(LAWS)), st.floats(-np.pi, np.pi), st.floats(-3, 3), st.floats(-3, 3),
       st.integers(0, 1000))
@example("coulomb", 0.59375, 0.0, 0.0, 104)  # found on a clean checkout: spin 1.5e-7 rad/s apart after 12 changes
def test_a_rigidly_moved_scene_gives_the_moved_result(law_name, angle, tx, ty, seed):
    """Rotate and translate the cells (and their wheel directions), the wheel field and the parcel's start by one
    rigid motion: the trajectory is the same rigid motion of the original one (heading shifted by the angle).

    Not to rounding: the pattern cache solves supports in coordinates rounded to 1e-9 pitches (1e-10 m here), and
    rounding differs between the frames, so support changes come up to ~1e-8 s apart; under Coulomb friction the
    accelerations jump at each change, so velocities drift apart by up to ~1e-8 m/s and rad/s a change (measured
    over 143 scenes: poses within 2e-8, velocities within 8e-8, the worst found 1.5e-7 rad/s)."""
    rng = np.random.default_rng(seed)
    cells = layout.grid(9, 7, 0.1)
    spec = parcel.rectangle(0.33, 0.27, 1.2, 0.6 if law_name != "viscous" else 1.0, mu_static=None)
    V = rng.uniform(-0.4, 0.4, size=(cells.n, 2))
    y0 = np.array([0.42, 0.31, rng.uniform(-0.5, 0.5), rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.3])
    law = LAWS[law_name]
    a = simulate(cells, spec, V, law, y0)
    R = rot(angle)
    t = np.array([tx, ty])
    moved_cells = layout.CellArray(cells.positions @ R.T + t, cells.drive_directions @ R.T, cells.pitch)
    z0 = np.r_[R @ y0[:2] + t, y0[2] + angle, R @ y0[3:5], y0[5]]
    b = simulate(moved_cells, spec, V @ R.T, law, z0)
    assert a.status == b.status and len(a.events) == len(b.events)
    np.testing.assert_allclose(b.states[:, :2], a.states[:, :2] @ R.T + t, atol=1e-7)
    np.testing.assert_allclose(b.states[:, 2], a.states[:, 2] + angle, atol=1e-7)
    np.testing.assert_allclose(b.states[:, 3:5], a.states[:, 3:5] @ R.T, atol=1e-6)
    np.testing.assert_allclose(b.states[:, 5], a.states[:, 5], atol=1e-6)


def test_cell_numbering_does_not_matter():
    cells = layout.grid(9, 7, 0.1)
    rng = np.random.default_rng(4)
    V = rng.uniform(-0.4, 0.4, size=(cells.n, 2))
    perm = rng.permutation(cells.n)
    shuffled = layout.CellArray(cells.positions[perm], cells.drive_directions[perm], cells.pitch)
    spec = parcel.rectangle(0.33, 0.27, 1.2, 1.0)
    y0 = [0.42, 0.31, 0.2, 0.05, 0.0, 0.3]
    a = simulate(cells, spec, V, laws.ViscousLaw(), y0)
    b = simulate(shuffled, spec, V[perm], laws.ViscousLaw(), y0)
    np.testing.assert_allclose(a.states, b.states, atol=1e-9)
    # shuffled cell k is original cell perm[k]
    assert [tuple(sorted(perm[list(e.entered)].tolist())) for e in b.events] == [e.entered for e in a.events]


@pytest.mark.parametrize("name", sorted(bundled_scenarios()))
def test_bundled_scenarios_are_bit_reproducible(name):
    sc, _ = load_scenario(name)
    sc = sc.model_copy(update={"duration": min(sc.duration, 12.0)})  # long enough for every kind of event
    a, b = run(sc.build()), run(sc.build())
    for pa, pb in zip(a.parcels, b.parcels):
        assert np.array_equal(pa.trajectory.states, pb.trajectory.states)
        assert pa.trajectory.events == pb.trajectory.events


def test_an_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    target = tmp_path / "summary.json"
    real_fsync = os.fsync

    def dying_fsync(fd):
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(os, "fsync", dying_fsync)
    with pytest.raises(KeyboardInterrupt):
        io.write_atomic(target, json.dumps({"complete": True}))
    assert not target.exists() and list(tmp_path.iterdir()) == []
    monkeypatch.setattr(os, "fsync", real_fsync)
    target.write_text("old")
    monkeypatch.setattr(os, "fsync", dying_fsync)
    with pytest.raises(KeyboardInterrupt):
        io.write_atomic(target, "new")
    assert target.read_text() == "old"  # the previous complete file survives


def test_an_atomically_written_file_has_the_mode_open_gives(tmp_path):
    """mkstemp makes its files 0600; a run's tables and pictures are for others to read as any new file is."""
    files.write_atomic(tmp_path / "a.json", "{}")
    with open(tmp_path / "b.json", "w") as fh:
        fh.write("{}")
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == (tmp_path / "b.json").stat().st_mode & 0o777


def test_a_killed_networked_run_resumes_to_the_uninterrupted_result(tmp_path):
    """Kill a checkpointing run (a real process, SIGKILL) after its first checkpoint, resume it, and get exactly
    the files of an uninterrupted run (the summary differs only in wall time)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    scenario = tmp_path / "s.toml"
    text = _bundled_text("sorting_junction").replace("duration = 40.0", "duration = 8.0")
    scenario.write_text(text)
    exe = [sys.executable, "-m", "virtual_vehicle.ui.cli"]
    ref = tmp_path / "ref"
    subprocess.run([*exe, "run", str(scenario), "-o", str(ref), "--no-plot"], check=True, capture_output=True)
    ck = tmp_path / "run.ckpt"
    proc = subprocess.Popen([*exe, "run", str(scenario), "-o", str(tmp_path / "killed"), "--no-plot",
                             "--checkpoint", str(ck), "--checkpoint-every", "2"])
    deadline = time.time() + 120
    while not ck.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert ck.exists() and not (tmp_path / "killed" / "summary.json").exists()
    out = tmp_path / "resumed"
    subprocess.run([*exe, "resume", str(ck), "-o", str(out), "--no-plot"], check=True, capture_output=True)
    for name in ("trajectories.csv", "events.csv", "network.csv", "scenario.toml"):
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name
    a, b = (json.loads((d / "summary.json").read_text()) for d in (ref, out))
    for s in (a, b):
        s.pop("wall_time_s"), s.pop("real_time_factor")
    assert a == b


def test_resume_rejects_what_is_not_a_checkpoint(tmp_path):
    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app

    bad = tmp_path / "x.ckpt"
    bad.write_bytes(b"not a checkpoint")
    res = CliRunner().invoke(app, ["resume", str(bad)])
    assert res.exit_code == 2 and "not a virtual_vehicle checkpoint" in res.output
    res = CliRunner().invoke(app, ["run", "prototype_18", "--checkpoint", str(tmp_path / "c"),
                                   "--checkpoint-every", "0"])
    assert res.exit_code == 2 and "checkpoint-every" in res.output


@pytest.mark.parametrize("name", ["crossing_30x30", "stick_slip_pickup"])
def test_an_interrupted_constant_field_run_resumes_bit_for_bit(tmp_path, name):
    """A constant-field run cut at checkpoints: stopped after its first checkpoint and resumed, it gives exactly the
    checkpointed run's result; and cutting changes the trajectory only at rounding level (event-driven) or not at
    all in substance (time-stepping)."""
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import FieldRun, resume, run

    sc = load_scenario(name)[0]
    every = sc.duration / 3
    job = FieldRun(sc.build())
    assert job.step(every, None) and not job.done
    job.save(tmp_path / "a.ckpt", every)
    resumed = resume(tmp_path / "a.ckpt")
    whole = run(sc.build(), checkpoint=tmp_path / "b.ckpt", checkpoint_every=every)
    plain = run(sc.build())
    for r, w, p in zip(resumed.parcels, whole.parcels, plain.parcels):
        assert np.array_equal(r.trajectory.times, w.trajectory.times)
        assert np.array_equal(r.trajectory.states, w.trajectory.states)
        assert [e.t for e in r.trajectory.events] == [e.t for e in w.trajectory.events]
        assert r.trajectory.stats == w.trajectory.stats
        assert np.array_equal(p.trajectory.times, w.trajectory.times)
        assert np.allclose(p.trajectory.states, w.trajectory.states, rtol=0, atol=1e-6)


def _bundled_text(name):
    from virtual_vehicle.config.scenario import load_scenario

    return load_scenario(name)[1]
