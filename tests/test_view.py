"""The live viewer (``virtual-vehicle view``): what it records replays with ``run`` to the same tables, its page
refuses a request without the token and listens on 127.0.0.1, and in a real browser a paused run stops, a clicked
cell dies and a dropped parcel comes on."""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from virtual_vehicle.config.scenario import load_scenario, parse_text
from virtual_vehicle.run import tables
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.view import LiveRun, Viewer

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def short_junction(duration: float = 2.0):
    sc, _ = load_scenario("sorting_junction")
    return sc.model_copy(update={"duration": duration})


def same_tables(a, b) -> None:
    ta, tb = tables.build(a), tables.build(b)
    assert ta.keys() == tb.keys()
    for name in ta:
        assert ta[name].equals(tb[name]), name


def test_a_kill_a_drop_and_a_revival_replay_with_run_to_the_same_tables():
    live = LiveRun(short_junction())
    live.advance(0.5, budget=1e9)
    assert live.t == pytest.approx(0.5)
    cell = live.cell_at(0.45, 0.55)
    assert live.toggle(cell) == "kill" and live.dead()[cell]
    live.advance(0.3, budget=1e9)
    name = live.drop(entry=0, destination=1)
    assert name not in {p.name for p in short_junction().parcels}
    live.advance(0.3, budget=1e9)
    assert live.toggle(cell) == "revive" and not live.dead()[cell]
    result = live.result()
    sc = parse_text(result.scenario_text)
    kill, revive = sc.faults.events
    assert (kill.t, kill.dead_cells) == (pytest.approx(0.5), [cell])
    assert (revive.t, revive.revived_cells) == (pytest.approx(1.1), [cell])
    dropped = sc.parcels[-1]
    assert (dropped.name, dropped.t_start, dropped.destination) == (name, pytest.approx(0.8), 1)
    assert [a["kind"] for a in live.actions] == ["kill", "drop", "revive"]
    same_tables(result, run(sc.build(), scenario_text=result.scenario_text))
    with pytest.raises(ValueError, match="ended"):
        live.toggle(cell)


def test_a_cell_killed_at_the_start_is_listed_dead_and_nothing_done_keeps_the_file():
    live = LiveRun("sorting_junction")
    assert live.scenario_text == load_scenario("sorting_junction")[1]
    live.toggle(5)
    assert live.scenario.faults.dead_cells == [5] and not live.scenario.faults.events and live.dead()[5]
    live.toggle(5)
    assert live.scenario.faults.dead_cells == [] and not live.dead()[5]


def test_steering_outside_the_array_or_its_lanes_is_refused():
    live = LiveRun(short_junction())
    assert live.cell_at(-1.0, -1.0) is None
    with pytest.raises(ValueError, match="no cell"):
        live.toggle(10_000)
    with pytest.raises(ValueError, match="no entry"):
        live.drop(entry=3)
    with pytest.raises(ValueError, match="no exit"):
        live.drop(entry=0, destination=3)
    assert live.actions == []
    with pytest.raises(ValueError, match=r"\[control\]"):
        LiveRun("paper_2x2_inward")


@pytest.fixture
def viewer():
    """A viewer of a short sorting run served on its own loop in a thread."""
    made = {}
    ready = threading.Event()

    def serve():
        asyncio.set_event_loop(asyncio.new_event_loop())
        v = Viewer(LiveRun(short_junction()))
        v.playing = False
        v.start()
        made["viewer"] = v
        ready.set()
        v.loop.start()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    assert ready.wait(60)
    v = made["viewer"]
    yield v
    v.loop.add_callback(v.stop)
    v.loop.add_callback(v.loop.stop)
    thread.join(10)


def status(url: str) -> int:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_the_page_needs_its_token(viewer):
    base = f"http://127.0.0.1:{viewer.port}/"
    assert status(viewer.url) == 200
    assert status(base) == 403
    assert status(base + "?bokeh-session-id=" + viewer.token[:-4] + "AAAA") == 403


def test_it_listens_on_127_0_0_1_only(viewer):
    assert viewer.url.startswith(f"http://127.0.0.1:{viewer.port}/?bokeh-session-id=")
    tcp = Path("/proc/net/tcp")
    if not tcp.exists():
        pytest.skip("no /proc/net/tcp to read the listening address from")
    listening = [line.split()[1] for line in tcp.read_text().splitlines()[1:] if line.split()[3] == "0A"]
    mine = [a for a in listening if int(a.split(":")[1], 16) == viewer.port]
    assert mine == ["0100007F:%04X" % viewer.port]  # 127.0.0.1 in the kernel's byte order, nothing else


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (Debian package chromium: the Makefile's set-up "
                    "installs it where it can)")
def test_in_a_browser_pause_kill_a_cell_and_drop_a_parcel(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright is a dev dependency")
    out = tmp_path / "view"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1] / "src"),
                                                         os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "virtual_vehicle.ui.cli", "view", "sorting_junction", "--out",
                             str(out), "--format", "csv", "--no-plot"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    try:
        url = None
        for line in proc.stdout:
            found = re.search(r"http://\S+", line)
            if found:
                url = found.group(0)
                break
        assert url is not None and url.startswith("http://127.0.0.1:")
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync"])
            page = browser.new_page(viewport={"width": 1500, "height": 950})
            page.goto(url)
            line = page.locator("text=/on the array [1-9]/")
            line.wait_for(timeout=120_000)  # parcels drawn
            page.get_by_role("button", name="pause").click()
            page.locator("text=paused").wait_for(timeout=30_000)
            t = re.search(r"t = ([0-9.]+) s", line.inner_text()).group(1)
            time.sleep(1.5)
            assert re.search(r"t = ([0-9.]+) s", line.inner_text()).group(1) == t  # simulated time stopped
            box = page.locator("canvas").first.bounding_box()
            page.mouse.click(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.45)
            killed = page.locator("text=/kill cell [0-9]+/")
            killed.wait_for(timeout=30_000)
            cell = int(re.search(r"kill cell ([0-9]+)", killed.inner_text()).group(1))
            assert f"t={float(t):g} s: kill cell {cell}" in killed.inner_text()
            page.get_by_role("button", name="drop a parcel").click()
            page.locator("text=/drop v00 at entry 0 for exit 0/").wait_for(timeout=120_000)
            page.screenshot(path=str(tmp_path / "paused.png"))
            page.get_by_role("button", name="play").click()
            page.wait_for_function(  # drawn on the array (the page's parcel source), with its destination
                "() => Bokeh.documents[0].get_model_by_name('parcels').data.label.includes('v00→0')", timeout=120_000)
            browser.close()
        proc.send_signal(signal.SIGINT)  # finish the run and write it
        _, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
    sc = parse_text((out / "scenario.toml").read_text())
    event = sc.faults.events[0]
    assert (event.t, event.dead_cells) == (pytest.approx(float(t)), [cell])
    assert sc.parcels[-1].name == "v00"
    again = tmp_path / "again"
    subprocess.run([sys.executable, "-m", "virtual_vehicle.ui.cli", "run", str(out / "scenario.toml"), "--out",
                    str(again), "--format", "csv", "--no-plot"], check=True, env=env, capture_output=True)
    for name in ("trajectories", "events", "network", "cell_traffic"):
        assert (out / f"{name}.csv").read_bytes() == (again / f"{name}.csv").read_bytes(), name


def a_run_folder(folder: Path, kill_at: float = 0.5):
    """A short sorting run with a cell killed at ``kill_at`` s, written to ``folder``; returns the cell killed and
    the poses of the parcels on the array at 1 s, by name, as the live run had them."""
    from virtual_vehicle.run.io import write_results

    live = LiveRun(short_junction())
    live.advance(kill_at, budget=1e9)
    cell = live.cell_at(0.45, 0.55)
    live.toggle(cell)
    live.advance(1.0 - live.t, budget=1e9)
    poses = {live.run.setup.specs[i].name: tuple(live.run.ys[i][:3]) for i in live.run.on}
    result = live.result()
    write_results(result, folder, result.scenario_text, formats=("csv",))
    return cell, poses


def test_a_replay_shows_the_parcels_and_cells_the_run_had_at_a_time(tmp_path):
    from virtual_vehicle.ui.view.replay import Replay

    cell, poses = a_run_folder(tmp_path / "run")
    replay = Replay(tmp_path / "run")
    frame = replay.frame(1.0)
    assert poses and frame.poses.keys() == poses.keys()
    for name, pose in poses.items():
        assert frame.poses[name] == pytest.approx(pose, abs=1e-9), name
    assert not replay.frame(0.45).dead[cell] and replay.frame(0.55).dead[cell]
    assert frame.lit.any() and not frame.lit_recorded  # no cell log: the sensors under the parcels
    replay.seek(99.0)
    assert replay.t == replay.duration and replay.done


def test_a_folder_that_is_not_a_run_is_refused_by_name(tmp_path):
    from typer.testing import CliRunner

    from virtual_vehicle.ui.cli import app
    from virtual_vehicle.ui.view.replay import Replay

    (tmp_path / "scenario.toml").write_text("")
    with pytest.raises(ValueError, match="not a run folder.*summary.json, trajectories"):
        Replay(tmp_path)
    res = CliRunner().invoke(app, ["view", str(tmp_path)])
    assert res.exit_code != 0 and "not a run folder" in res.output


def test_a_frame_sends_only_what_changed():
    from bokeh.document import Document

    from virtual_vehicle.ui.view import page

    live = LiveRun(short_junction())
    viewer = type("V", (), {"live": live, "playing": False, "speed": 1.0, "frame": 0.1, "message": "",
                            "step_once": lambda self: None})()
    doc = Document()
    refresh = page.build(doc, viewer)
    live.advance(1.0, budget=1e9)
    refresh()
    sent = []
    doc.callbacks.on_change(lambda event: sent.append(event))
    refresh()  # nothing moved: the array's sources are left alone
    array = {"cells", "parcels", "waiting", "sensors", "wheels"}
    assert not [e for e in sent if getattr(e, "model", None) is not None and e.model.name in array]
    assert len(doc.get_model_by_name("wheels").data["x0"]) > 0  # a small array draws its wheels' arrows
    live.toggle(live.cell_at(0.45, 0.55))
    refresh()  # one cell turned black: the image is patched there, not sent again
    cells = [e for e in sent if getattr(e, "model", None) is not None and e.model.name == "cells"]
    assert [type(e).__name__ for e in cells] == ["ColumnsPatchedEvent"]
    image = doc.get_model_by_name("cells").data["image"][0]
    (where, block), = cells[0].patches["image"]
    assert 0 < block.size < image.size / 4


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (Debian package chromium: the Makefile's set-up "
                    "installs it where it can)")
def test_in_a_browser_a_run_folder_replays_at_the_time_scrubbed_to(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright is a dev dependency")
    from virtual_vehicle.ui.view.replay import Replay

    a_run_folder(tmp_path / "run")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1] / "src"),
                                                         os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "virtual_vehicle.ui.cli", "view", str(tmp_path / "run"),
                             "--paused"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        url = next((m.group(0) for line in proc.stdout if (m := re.search(r"http://\S+", line))), None)
        assert url is not None and url.startswith("http://127.0.0.1:")
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
            page = browser.new_page(viewport={"width": 1500, "height": 950})
            page.goto(url)
            page.locator("text=/t = 0.00 s of 2 s/").wait_for(timeout=120_000)
            page.evaluate("() => { Bokeh.documents[0].get_model_by_name('time').value = 1.0 }")  # the scrubber
            page.locator("text=/t = 1.00 s of 2 s/").wait_for(timeout=30_000)
            want = json.dumps(sorted(Replay(tmp_path / "run").frame(1.0).poses), separators=(",", ":"))
            page.wait_for_function("() => JSON.stringify(Bokeh.documents[0].get_model_by_name('parcels').data.label"
                                   f".map(l => l.split('→')[0]).sort()) === '{want}'", timeout=30_000)
            page.screenshot(path=str(tmp_path / "replay.png"))
            page.get_by_role("button", name="play").click()
            page.locator("text=/t = 2.00 s of 2 s/").wait_for(timeout=60_000)  # played to the end
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    assert proc.returncode == 0


def test_the_page_flags_the_stall_the_run_report_finds():
    """A wall of cells dies across the lane at 2 s: the first parcel stops at it, the next stops behind, and the
    viewer calls them one waiting group as the run's report does (a queue stalled behind a parcel that waits on dead
    cells: no cycle of holds, so no deadlock)."""
    from virtual_vehicle.config.scenario import FaultEvent

    sc = short_junction(7.0)
    P = sc.build().cells.positions
    wall = [int(i) for i in ((P[:, 0] > 1.1) & (P[:, 0] < 1.25)).nonzero()[0]]
    sc = sc.model_copy(update={"control": sc.control.model_copy(update={"wait_bound": 1.0}),
                               "faults": sc.faults.model_copy(update={"events": [FaultEvent(t=2.0, dead_cells=wall)]})})
    live = LiveRun(sc)
    live.advance(3.0, budget=1e9)
    assert live.stalls() == []  # moving until the wall
    while not live.done:
        live.advance(0.25, budget=1e9)
        seen = live.stalls()
    report = live.result().summary()["sorting"]["stalls"]
    assert [(s["kind"], s["parcels"]) for s in seen] == [(s["kind"], s["parcels"]) for s in report]
    assert [s["kind"] for s in seen] == ["waiting"] and len(seen[0]["parcels"]) >= 2


def test_a_parcel_given_a_new_target_on_the_page_goes_there_and_replays_with_run():
    from bokeh.document import Document
    from bokeh.events import Tap

    from virtual_vehicle.ui.view import page

    sc, _ = load_scenario("pose_tasks")
    live = LiveRun(sc.model_copy(update={"duration": 3.0}))
    viewer = type("V", (), {"live": live, "playing": False, "speed": 1.0, "frame": 0.1, "message": "",
                            "step_once": lambda self: None})()
    doc = Document()
    refresh = page.build(doc, viewer)
    live.advance(1.0, budget=1e9)
    doc.get_model_by_name("target parcel").value = "move"
    doc.get_model_by_name("target heading").value = 0.0
    doc.get_model_by_name("aim").active = True
    array = doc.get_model_by_name("array")
    array._trigger_event(Tap(array, x=0.6, y=0.3))  # a click on the array at (0.6, 0.3) m
    refresh()
    assert live.actions == [{"t": pytest.approx(1.0), "kind": "target", "parcel": "move", "target": (0.6, 0.3, 0.0)}]
    assert "move target" in doc.get_model_by_name("targets").data["label"]
    live.advance(1.5, budget=1e9)
    result = live.result()
    assert result.parcels[0].trajectory.states[-1][:2] == pytest.approx([0.6, 0.3], abs=0.015)
    written = parse_text(result.scenario_text)
    (change,) = written.control.retargets
    assert (change.t, change.parcel, change.target) == (pytest.approx(1.0), "move", (0.6, 0.3, 0.0))
    assert result.summary()["parcels"][0]["target"] == {"x": 0.6, "y": 0.3, "theta": 0.0}
    same_tables(result, run(written.build(), scenario_text=result.scenario_text))
    with pytest.raises(ValueError, match="no parcel named"):
        LiveRun("pose_tasks").retarget("nobody", (0.5, 0.5, 0.0))
    with pytest.raises(ValueError, match="no target poses"):
        LiveRun(short_junction()).retarget("p00", (0.5, 0.5, 0.0))


def test_a_field_run_replays_too(tmp_path):
    """A run without a network (no arrivals reported: its parcels are on from their first sample) replays its
    parcels where its trajectories have them, with plain cells."""
    from virtual_vehicle.run.io import write_results
    from virtual_vehicle.ui.view.replay import Replay

    result = run(load_scenario("paper_2x2_inward")[0].build())
    write_results(result, tmp_path, formats=("parquet",))
    replay = Replay(tmp_path)
    tr = result.parcels[0].trajectory
    t = float(tr.times[len(tr.times) // 2])
    frame = replay.frame(t)
    assert frame.poses[result.parcels[0].spec.name] == pytest.approx(tuple(tr.states[len(tr.times) // 2, :3]))
    assert frame.traffic is None and frame.wheels is None and not frame.waiting
