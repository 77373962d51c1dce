"""Animations: what each frame shows is what the run did, and the video files are whole and of the right length."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui import animate as anim
from virtual_vehicle.ui.cli import app


def _run(name: str, duration: float, record: bool = True):
    sc, _ = load_scenario(name)
    update = {"duration": duration}
    if record:
        update["sensors"] = sc.sensors.model_copy(update={"record": True})
    return run(sc.model_copy(update=update).build())


@pytest.fixture(scope="module")
def field_run():
    return _run("prototype_18", 2.0, record=False)


@pytest.fixture(scope="module")
def sorting_run():
    return _run("sorting_junction", 6.0)


def test_constant_field_frames_show_the_field_and_the_covered_sensors(field_run):
    r = field_run
    times = np.array([0.0, 0.37, 1.5, 2.0])
    d = anim.frame_data(r, times)
    setup = r.setup
    tr = r.parcels[0].trajectory
    for f, t in enumerate(times):
        pose = [np.interp(t, tr.times, tr.states[:, j]) for j in range(3)]
        np.testing.assert_allclose(d.poses[f, 0], pose)
        state = np.array([*pose, 0.0, 0.0, 0.0])
        np.testing.assert_array_equal(d.lit[f], setup.sensors.covered(setup.specs, [state]))
        assert d.lit[f].any()
        # each wheel's speed along its drive direction recombines into the cell's field velocity
        V = np.einsum("ik,ikj->ij", d.wheel_speeds[f], setup.cells.drive_directions)
        np.testing.assert_allclose(V, setup.velocities, atol=1e-15)
    assert d.traffic is None


def test_networked_frames_come_from_the_cell_log(sorting_run):
    r = sorting_run
    log = r.cell_log
    period = r.setup.control.period
    times = np.array([0.0, 1.234, 3.0, 5.999])
    d = anim.frame_data(r, times, window=0.2)
    for f, t in enumerate(times):
        k = int(np.searchsorted(log.t, t, side="right") - 1)
        assert log.t[k] <= t < log.t[k] + period + 1e-12
        np.testing.assert_array_equal(d.lit[f], log.readings[k])
        np.testing.assert_array_equal(d.wheel_speeds[f], log.commands[k])
        lo = max(0, k + 1 - round(0.2 / period))
        np.testing.assert_allclose(d.traffic[f], log.received[lo:k + 1].sum(axis=0) / ((k + 1 - lo) * period))
    assert d.traffic.max() > 0
    # parcels appear when put on and vanish when gone
    for p, pr in enumerate(r.parcels):
        tr = pr.trajectory
        for f, t in enumerate(times):
            on = pr.entered_at is not None and tr.times[0] <= t <= tr.times[-1]
            assert np.isfinite(d.poses[f, p, 0]) == on


def test_a_networked_run_without_a_cell_log_is_refused():
    r = _run("prototype_18_network_ideal", 0.2, record=False)
    with pytest.raises(ValueError, match="record = true"):
        anim.frame_data(r, [0.0])


@pytest.mark.skipif(anim.ffmpeg_exe() is None, reason="no ffmpeg")
def test_mp4_has_one_frame_per_step_of_video(field_run, tmp_path):
    import imageio_ffmpeg

    out = anim.animate(field_run, tmp_path / "a.mp4", fps=10, speed=1.0)
    assert out == tmp_path / "a.mp4"
    frames, secs = imageio_ffmpeg.count_frames_and_secs(str(out))
    assert frames == 21 and secs == pytest.approx(2.1, abs=0.11)  # t = 0, 0.1, ..., 2.0 s
    assert [p.name for p in tmp_path.iterdir()] == ["a.mp4"]  # no temporary left behind


def test_without_ffmpeg_an_mp4_falls_back_to_a_gif(field_run, tmp_path, monkeypatch):
    monkeypatch.setattr(anim, "ffmpeg_exe", lambda: None)
    with pytest.warns(UserWarning, match="GIF"):
        out = anim.animate(field_run, tmp_path / "a.mp4", fps=4, speed=2.0, start=0.5)
    assert out == tmp_path / "a.gif"
    with Image.open(out) as im:
        assert im.n_frames == 4  # t = 0.5, 1.0, 1.5, 2.0 s
        assert im.size[0] % 2 == 0 and im.size[1] % 2 == 0


@pytest.mark.parametrize("kwargs, message", [
    ({"path": "a.avi"}, "must end in"),
    ({"fps": 0}, "positive"),
    ({"start": 1.5, "end": 1.0}, "start < end"),
    ({"end": 9.0}, "start < end"),
])
def test_bad_animation_requests_are_refused(field_run, tmp_path, kwargs, message):
    path = tmp_path / kwargs.pop("path", "a.gif")
    with pytest.raises(ValueError, match=message):
        anim.animate(field_run, path, **kwargs)
    assert not any(tmp_path.iterdir())


def test_the_animate_command_records_a_networked_run(tmp_path):
    out = tmp_path / "net.gif"
    res = CliRunner().invoke(app, ["animate", "prototype_18_network_ideal", "--out", str(out), "--end", "0.5",
                                   "--fps", "6"])
    assert res.exit_code == 0, res.output
    with Image.open(out) as im:
        assert im.n_frames == 4  # t = 0, 1/6, 2/6, 3/6 s
    res = CliRunner().invoke(app, ["animate", "prototype_18", "--out", str(tmp_path / "x.gif"), "--start", "5",
                                   "--end", "1"])
    assert res.exit_code == 2 and "--start/--end" in res.output


@pytest.mark.parametrize("args, message", [
    (["--fps", "100000"], "--fps"),
    (["--fps", "0.01"], "--fps"),
    (["--fps", "120", "--speed", "0.001"], "frames, more than"),
])
def test_the_animate_command_bounds_fps_and_frames_before_simulating(tmp_path, args, message):
    out = tmp_path / "a.mp4"
    res = CliRunner().invoke(app, ["animate", "prototype_18", "--out", str(out), *args])
    assert res.exit_code == 2, res.output
    assert message in res.output and "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())


def test_an_interrupted_animation_leaves_no_file_and_says_how_far_it_got(field_run, tmp_path, monkeypatch):
    calls = []

    def grab(self, **kwargs):  # the third frame is interrupted, as by Ctrl-C
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return original(self, **kwargs)

    original = anim.PillowWriter.grab_frame
    monkeypatch.setattr(anim.PillowWriter, "grab_frame", grab)
    with pytest.raises(anim.AnimationInterrupted) as info:
        anim.animate(field_run, tmp_path / "a.gif", fps=5)
    assert (info.value.frames, info.value.total) == (3, 11)
    assert not any(tmp_path.iterdir())  # neither the target nor a hidden partial file


@pytest.mark.skipif(anim.ffmpeg_exe() is None, reason="no ffmpeg")
def test_what_ffmpeg_says_is_passed_on_after_a_video_and_dropped_after_an_interrupt(field_run, tmp_path, caplog):
    """matplotlib logs ffmpeg's command and its stderr; after Ctrl-C that is noise (ffmpeg complains of the frame it
    was cut off in), so it is dropped, every record of it, not only those after the first."""
    caplog.set_level("DEBUG", logger="matplotlib.animation")
    anim.animate(field_run, tmp_path / "a.mp4", fps=5)
    said = [r.getMessage() for r in caplog.records if r.name == "matplotlib.animation"]
    assert any(m.startswith("MovieWriter._run") for m in said) and any("MovieWriter stderr" in m for m in said)
    caplog.clear()

    def stop(fraction):
        raise KeyboardInterrupt

    with pytest.raises(anim.AnimationInterrupted):
        anim.animate(field_run, tmp_path / "b.mp4", fps=5, progress=stop)
    assert [r for r in caplog.records if r.name == "matplotlib.animation"] == []


@pytest.mark.skipif(anim.ffmpeg_exe() is None, reason="no ffmpeg")
def test_ctrl_c_in_the_animate_command_stops_cleanly(tmp_path):
    """SIGINT to the whole process group (as a terminal's Ctrl-C: ffmpeg gets it too) while frames are drawn."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    import virtual_vehicle

    out = tmp_path / "a.mp4"
    env = {**os.environ, "PYTHONPATH": str(Path(virtual_vehicle.__file__).parents[1]), "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "virtual_vehicle.ui.cli", "animate", "prototype_18", "--out",
                             str(out), "--fps", "100", "--speed", "0.1"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env, start_new_session=True, text=True)
    try:
        deadline = time.monotonic() + 240
        while not any(tmp_path.glob(".a.*")) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # wait until the video is being written
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted after drawing" in stderr
    assert len([line for line in stderr.splitlines() if line.strip()]) == 1, stderr
    assert not any(tmp_path.iterdir())


def test_frames_draw_entries_exits_dead_cells_and_a_light_traffic_scale():
    sc, _ = load_scenario("sorting_junction")
    sc = sc.model_copy(update={"duration": 1.0, "sensors": sc.sensors.model_copy(update={"record": True}),
                               "faults": type(sc.faults).model_validate({"dead_cells": [30], "events": [
                                   {"t": 0.5, "dead_cells": [100]}]})})
    r = run(sc.build())
    data = anim.frame_data(r, np.array([0.0, 0.3, 0.7]))
    fig, update = anim.scene(r, data)
    ax = fig.axes[0]
    names = {t.get_text() for t in ax.texts}
    assert {"entry", "exit 0", "exit 1", "exit 2"} <= names
    (crosses,) = [c for c in ax.collections if c.get_gid() == "dead-cells"]
    for f, dead in ((1, {30}), (2, {30, 100})):  # the cell that dies at 0.5 s is crossed out from then on
        update(f)
        shown = set(np.flatnonzero(crosses.get_edgecolors()[:, 3] > 0))
        assert shown == dead
    tiles = ax.collections[0]
    lo, hi = tiles.get_clim()
    assert (lo, hi) == anim.traffic_range(data) and lo > 0  # the common level is near white, not mid-purple
    assert min(anim.TRAFFIC_CMAP(0.0)[:3]) > 0.9 and tiles.get_alpha() < 1
