"""Sweeps on Dask: every variation run once, failures recorded, interrupted sweeps resumed, results equal to runs."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from virtual_vehicle import sweep as sw
from virtual_vehicle.cli import app
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.scenario import load_scenario
from virtual_vehicle.sim import run

SWEEP = """base = "prototype_18"
[vary]
"duration" = [0.5, 1.0]
"parcels.*.mu" = [0.3, 0.6, -1.0]
"""


def test_a_grid_sweep_runs_every_variation_records_failures_and_resumes(tmp_path):
    spec_file = tmp_path / "sweep.toml"
    spec_file.write_text(SWEEP)
    res = CliRunner().invoke(app, ["sweep", str(spec_file), "--out", str(tmp_path / "out"), "--workers", "2"])
    assert res.exit_code == 0, res.output
    table = pd.read_parquet(tmp_path / "out" / "summary.parquet")
    assert len(table) == 6
    assert sorted(zip(table["vary.duration"], table["vary.parcels.*.mu"])) == sorted(
        (d, m) for d in (0.5, 1.0) for m in (0.3, 0.6, -1.0))
    bad = table[table["vary.parcels.*.mu"] < 0]
    assert (bad["status"] == "error").all() and bad["error"].str.contains("mu").all()
    # each good row is what a direct run of that variation gives, bit for bit
    base, _ = load_scenario("prototype_18")
    for _, row in table[table["status"] == "ok"].iterrows():
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
    assert (again["runs"], again["ran"], again["skipped"], again["failed"]) == (6, 1, 5, 2)
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


def test_the_documented_sweep_file_is_valid(tmp_path):
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "sweeps.md").read_text()
    (block,) = re.findall(r"```toml\n(.*?)```", page, flags=re.S)
    (tmp_path / "study.toml").write_text(block)
    spec, base = sw.load_sweep(tmp_path / "study.toml")
    rows = spec.variations()
    assert len(rows) == 40 and all(0.0 <= r["control.loss_rate"] <= 0.3 for r in rows)
    from virtual_vehicle.scenario import parse_scenario

    parse_scenario(sw.apply(base, rows[0])).build()
