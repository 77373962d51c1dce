"""Sweeps on Dask: every variation run once, failures recorded, interrupted sweeps resumed, results equal to runs."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from virtual_vehicle.analysis import sweep as sw
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.cli import app

SWEEP = """base = "prototype_18"
[vary]
"duration" = [0.5, 1.0]
"parcels.*.mu" = [0.3, 0.6, 0.9]
"""


def test_a_grid_sweep_runs_every_variation_and_resumes(tmp_path):
    spec_file = tmp_path / "sweep.toml"
    spec_file.write_text(SWEEP)
    res = CliRunner().invoke(app, ["sweep", str(spec_file), "--out", str(tmp_path / "out"), "--workers", "2"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "out" / "summary.parquet")
    assert len(table) == 6 and (table["status"] == "ok").all() and (table["attempts"] == 1).all()
    assert sorted(zip(table["vary.duration"], table["vary.parcels.*.mu"])) == sorted(
        (d, m) for d in (0.5, 1.0) for m in (0.3, 0.6, 0.9))
    # each row is what a direct run of that variation gives, bit for bit
    base, _ = load_scenario("prototype_18")
    for _, row in table.iterrows():
        parcels = [p.model_copy(update={"mu": row["vary.parcels.*.mu"]}) for p in base.parcels]
        direct = run(base.model_copy(update={"duration": row["vary.duration"], "parcels": parcels}).build())
        assert row["parcel.bread_box.end.x"] == direct.parcels[0].trajectory.states[-1, 0]
        assert row["parcel.bread_box.support_changes"] == direct.summary()["parcels"][0]["support_changes"]
    # resume: only the missing run is redone, and the table is the same
    runs = sorted((tmp_path / "out" / "runs").glob("*.json"))
    assert len(runs) == 6
    runs[2].unlink()
    spec, raw = sw.load_sweep(spec_file)
    again = sw.run_sweep(spec, raw, tmp_path / "out", workers=1)
    assert (again["runs"], again["ran"], again["skipped"], again["failed"]) == (6, 1, 5, 0)
    table2 = pd.read_parquet(tmp_path / "out" / "summary.parquet")
    timing = [c for c in table.columns if "wall_time" in c or "real_time" in c]
    pd.testing.assert_frame_equal(table.drop(columns=timing), table2.drop(columns=timing))


def test_an_existing_cluster_is_used_and_a_task_that_dies_is_recorded(tmp_path, monkeypatch):
    from dask.distributed import LocalCluster

    real = sw.run_variation

    def broken(base, variation):
        if variation["duration"] > 0.7:
            raise RuntimeError("worker lost")
        return real(base, variation)

    monkeypatch.setattr(sw, "run_variation", broken)
    spec = sw.SweepSpec(base="prototype_18", vary={"duration": [0.5, 1.0]})
    _, text = load_scenario("prototype_18")
    import tomllib

    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        res = sw.run_sweep(spec, tomllib.loads(text), tmp_path, scheduler=cluster.scheduler_address)
    assert (res["runs"], res["failed"]) == (2, 1)
    rows = [json.loads(p.read_text()) for p in (tmp_path / "runs").glob("*.json")]
    failed = [r for r in rows if r["status"] == "error"]
    assert len(failed) == 1 and "worker lost" in failed[0]["error"] and failed[0]["vary.duration"] == 1.0


def test_random_sweeps_are_reproducible_and_stay_in_their_ranges():
    spec = sw.SweepSpec(base="x", mode="random", samples=200, seed=7,
                        vary={"a": {"min": 0.1, "max": 0.2}, "b": {"min": 0, "max": 3, "integer": True},
                              "c": ["u", "v"]})
    rows = spec.variations()
    assert rows == sw.SweepSpec.model_validate(spec.model_dump()).variations()
    assert rows != spec.model_copy(update={"seed": 8}).variations()
    a = np.array([r["a"] for r in rows])
    assert a.min() >= 0.1 and a.max() <= 0.2
    assert {r["b"] for r in rows} == {0, 1, 2, 3}
    assert {r["c"] for r in rows} == {"u", "v"}
    with pytest.raises(ScenarioError, match="grid"):
        sw.SweepSpec(base="x", vary={"a": {"min": 0, "max": 1}}).variations()


def test_dotted_paths_reach_tables_list_items_and_every_item():
    base = {"duration": 1.0, "control": {"loss_rate": 0.0}, "parcels": [{"mu": 0.5}, {"mu": 0.5}]}
    out = sw.apply(base, {"control.loss_rate": 0.1, "parcels.1.mu": 0.2, "duration": 3.0})
    assert out == {"duration": 3.0, "control": {"loss_rate": 0.1}, "parcels": [{"mu": 0.5}, {"mu": 0.2}]}
    assert sw.apply(base, {"parcels.*.mu": 0.9})["parcels"] == [{"mu": 0.9}, {"mu": 0.9}]
    assert base["parcels"][1]["mu"] == 0.5  # the base is not changed
    with pytest.raises(ScenarioError, match="index"):
        sw.apply(base, {"parcels.5.mu": 1.0})
    with pytest.raises(ScenarioError, match="not a table"):
        sw.apply(base, {"duration.x": 1.0})


def test_bad_sweep_files_exit_2(tmp_path):
    cases = {"no_vary.toml": 'base = "prototype_18"\n', "bad_mode.toml": 'base = "prototype_18"\nmode = "all"\n'
             '[vary]\n"duration" = [1.0]\n', "no_base.toml": 'base = "nope"\n[vary]\n"duration" = [1.0]\n',
             "broken.toml": "base = \n"}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        res = CliRunner().invoke(app, ["sweep", str(tmp_path / name), "--out", str(tmp_path / "o")])
        assert res.exit_code == 2, (name, res.output)
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("vary, path, message", [
    ('"frictio.law" = ["viscous"]', "frictio.law", "unknown field"),  # a misspelt table
    ('"parcels.0.muu" = [0.5]', "parcels.0.muu", "unknown field"),  # a misspelt field of a list item
    ('"duration" = [1.0, 2.0]\n"parcels.*.mu" = [0.5, -1.0]', "parcels.*.mu", "greater than 0"),  # one bad value
    ('"parcels.0.x" = [0.2, 100.0]', "parcels.0.x", "off the array"),  # caught only by building the scenario
    ('"parcels.3.mu" = [0.5]', "parcels.3.mu", "index"),  # the prototype has one parcel
])
def test_a_bad_vary_path_or_value_stops_the_sweep_before_anything_runs(tmp_path, vary, path, message):
    (tmp_path / "s.toml").write_text(f'base = "prototype_18"\n[vary]\n{vary}\n')
    res = CliRunner().invoke(app, ["sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert f"vary.{path}:" in res.output and message in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()  # nothing ran


def test_an_unreachable_scheduler_is_one_message_and_exit_2(tmp_path):
    import socket

    with socket.socket() as s:  # a port nothing listens on once this socket is closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "s.toml").write_text(SWEEP)
    res = CliRunner().invoke(app, ["sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"),
                                   "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert res.exit_code == 2, res.output
    assert f"no Dask scheduler answered at 'tcp://127.0.0.1:{port}' within {sw.CONNECT_TIMEOUT_S:g} s" in res.output
    assert res.output.count("\n") <= 2 and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()


def test_the_documented_sweep_file_is_valid(tmp_path):
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "sweeps.md").read_text()
    (block,) = re.findall(r"```toml\n(.*?)```", page, flags=re.S)
    (tmp_path / "study.toml").write_text(block)
    spec, base = sw.load_sweep(tmp_path / "study.toml")
    rows = spec.variations()
    assert len(rows) == 40 and all(0.0 <= r["control.loss_rate"] <= 0.3 for r in rows)
    from virtual_vehicle.config.scenario import parse_scenario

    parse_scenario(sw.apply(base, rows[0])).build()


def _raw(name):
    import tomllib

    return tomllib.loads(load_scenario(name)[1])


def test_two_sweeps_at_once_on_one_cluster_keep_their_own_scenarios(tmp_path):
    """Two sweep commands (two processes, as two users' would be) against one scheduler on 127.0.0.1 at once."""
    import subprocess
    import sys
    from pathlib import Path

    from dask.distributed import LocalCluster

    sweeps = {"prototype_18": 18, "paper_2x2_inward": 4}  # base scenario -> its cell count
    env = {**__import__("os").environ, "PYTHONPATH": str(Path(sw.__file__).parents[2])}
    with LocalCluster(host="127.0.0.1", processes=True, n_workers=2, threads_per_worker=1,
                      dashboard_address=None) as cluster:
        procs = {}
        for name in sweeps:
            spec = tmp_path / f"{name}.toml"
            spec.write_text(f'base = "{name}"\n[vary]\n"duration" = [0.1, 0.2, 0.3]\n')
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "virtual_vehicle.ui.cli", "sweep", str(spec), "--out", str(tmp_path / name),
                 "--scheduler", cluster.scheduler_address], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                text=True, env=env)
        try:
            outputs = {name: proc.communicate(timeout=300) for name, proc in procs.items()}  # a bound, not a timing
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
    for name, cells in sweeps.items():
        assert procs[name].returncode == 0, outputs[name]
        table = pd.read_parquet(tmp_path / name / "summary.parquet")
        assert len(table) == 3 and (table["status"] == "ok").all(), table
        assert set(table["scenario"]) == {name} and set(table["cells"]) == {cells}


def test_runs_lost_with_every_worker_are_run_again_and_the_base_scattered_again(tmp_path):
    import os
    import signal

    from dask.distributed import Client, LocalCluster

    spec = sw.SweepSpec(base="prototype_18", vary={"duration": [0.25 * k for k in range(1, 9)]})
    with LocalCluster(host="127.0.0.1", processes=True, n_workers=1, threads_per_worker=1,
                      dashboard_address=None) as cluster:
        with Client(cluster) as client:
            pids = list(client.run(os.getpid).values())
        killed = []

        def kill_the_workers(fraction):  # after the first run is written: its worker dies with the scattered base
            if not killed:
                for pid in pids:
                    os.kill(pid, signal.SIGKILL)
                killed.append(fraction)

        res = sw.run_sweep(spec, _raw("prototype_18"), tmp_path, scheduler=cluster.scheduler_address,
                           progress=kill_the_workers)
    assert killed and killed[0] < 1.0
    table = pd.read_parquet(res["summary"])
    assert (res["runs"], res["failed"], res["lost"]) == (8, 0, 0), table[["status", "error"]]
    assert (table["status"] == "ok").all() and table["attempts"].max() == 2  # the runs lost were tried again
    assert sorted(table["vary.duration"]) == [0.25 * k for k in range(1, 9)]


def test_runs_lost_too_often_are_recorded_as_lost_and_run_again_on_the_next_sweep(tmp_path, monkeypatch):
    from dask.distributed import LocalCluster
    from distributed.comm.core import CommClosedError

    real = sw.run_variation

    def flaky(base, variation):  # as a worker whose connection keeps dropping would look to the client
        if variation["duration"] > 0.7:
            raise CommClosedError("connection to the worker lost")
        return real(base, variation)

    monkeypatch.setattr(sw, "run_variation", flaky)
    spec = sw.SweepSpec(base="prototype_18", vary={"duration": [0.5, 1.0]})
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        res = sw.run_sweep(spec, _raw("prototype_18"), tmp_path, scheduler=cluster.scheduler_address)
        assert (res["runs"], res["failed"], res["lost"]) == (2, 1, 1)
        lost = pd.read_parquet(res["summary"]).set_index("vary.duration").loc[1.0]
        assert lost["status"] == "lost" and "connection" in lost["error"] and lost["attempts"] == sw.MAX_ATTEMPTS
        monkeypatch.setattr(sw, "run_variation", real)  # the cluster is well again: the lost run (only) runs
        again = sw.run_sweep(spec, _raw("prototype_18"), tmp_path, scheduler=cluster.scheduler_address)
    assert (again["ran"], again["skipped"], again["failed"]) == (1, 1, 0)


def test_failed_runs_exit_1_and_retry_failed_redoes_only_them(tmp_path, monkeypatch):
    from dask.distributed import LocalCluster

    real = sw.run_variation

    def broken(base, variation):
        if variation["duration"] > 0.7:
            raise RuntimeError("a bug in this run")
        return real(base, variation)

    (tmp_path / "s.toml").write_text(SWEEP)
    args = ["sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")]
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        args += ["--scheduler", cluster.scheduler_address]
        monkeypatch.setattr(sw, "run_variation", broken)
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 1 and "3 of 6 runs failed" in res.output and "--retry-failed" in res.output
        table = pd.read_parquet(tmp_path / "o" / "summary.parquet")
        assert (table["status"] == "error").sum() == 3 and table["error"].str.contains("a bug").sum() == 3
        finished = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "o" / "runs").glob("*.json")
                    if json.loads(p.read_text())["status"] == "ok"}
        monkeypatch.setattr(sw, "run_variation", real)  # the bug fixed
        res = CliRunner().invoke(app, args)  # without --retry-failed: failed rows stay
        assert res.exit_code == 1 and "0 run now, 6 already done" in res.output
        res = CliRunner().invoke(app, args + ["--retry-failed"])
    assert res.exit_code == 0 and "3 run now, 3 already done), 0 failed" in res.output, res.output
    assert (pd.read_parquet(tmp_path / "o" / "summary.parquet")["status"] == "ok").all()
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "o" / "runs").glob("*.json")
            if p.name in finished} == finished  # finished runs were not redone


def test_ctrl_c_stops_a_sweep_cleanly_and_keeps_its_finished_runs(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    (tmp_path / "s.toml").write_text('base = "sorting_junction"\n[vary]\n"duration" = [3.0]\n'
                                     '"control.seed" = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]\n')
    out = tmp_path / "o"
    env = {**os.environ, "PYTHONPATH": str(Path(sw.__file__).parents[2])}
    proc = subprocess.Popen([sys.executable, "-m", "virtual_vehicle.ui.cli", "sweep", str(tmp_path / "s.toml"),
                             "--out", str(out), "--workers", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 300  # a bound on the wait, not a timing assertion
        while not list(out.glob("runs/*.json")) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # as Ctrl-C in a terminal: the sweep and its workers
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, (stdout, stderr)
    assert "Traceback" not in stderr + stdout, stderr
    kept = sorted(out.glob("runs/*"))
    assert 1 <= len(kept) < 12 and all(p.suffix == ".json" and not p.name.startswith(".") for p in kept)
    assert all(json.loads(p.read_text())["status"] == "ok" for p in kept)  # each complete
    assert f"interrupted: {len(kept)} of 12 runs finished and kept in" in stderr and "to resume" in stderr
    assert not (out / "summary.parquet").exists()


def test_every_random_draw_is_its_own_run_even_when_two_draw_the_same_values():
    spec = sw.SweepSpec(base="paper_2x2_inward", mode="random", samples=10, vary={"parcels.0.mass": [1.0, 2.0]})
    variations = spec.variations()
    assert len({tuple(v.items()) for v in variations}) <= 2
    assert len(set(sw.sweep_ids(spec, variations, {"name": "b"}))) == 10
    grid = sw.SweepSpec(base="paper_2x2_inward", vary={"parcels.0.mass": [1.0, 2.0]})
    assert sw.sweep_ids(grid, grid.variations(), {"name": "b"}) == [sw.run_id(v, {"name": "b"})
                                                                    for v in grid.variations()]
