"""Results as data: Parquet and CSV tables with units, the run folder's manifest, and reproducing a run from its
folder alone."""

import csv
import hashlib
import json

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from virtual_vehicle.config.scenario import dump_toml, load_scenario, parse_scenario, parse_text
from virtual_vehicle.run import io, tables
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.cli import app


def _recorded(duration=0.5):
    sc, _ = load_scenario("prototype_18_network_ideal")
    d = sc.model_dump()
    d["sensors"]["record"] = True
    d["duration"] = duration
    return parse_scenario(d)


def test_parquet_tables_hold_the_run_exactly_with_units(tmp_path):
    res = run(load_scenario("crossing_30x30")[0].build())
    paths = io.write_results(res, tmp_path)
    traj = pd.read_parquet(paths["trajectories.parquet"])
    for pr in res.parcels:
        rows = traj[traj.parcel == pr.spec.name]
        assert np.array_equal(rows.t.to_numpy(), pr.trajectory.times)
        assert np.array_equal(rows[["x", "y", "theta", "vx", "vy", "omega"]].to_numpy(), pr.trajectory.states)
    schema = pq.read_schema(paths["trajectories.parquet"])
    assert {f.name: f.metadata[b"unit"].decode() for f in schema} == {
        "parcel": "", "t": "s", "x": "m", "y": "m", "theta": "rad", "vx": "m/s", "vy": "m/s", "omega": "rad/s"}
    ev = pd.read_parquet(paths["events.parquet"])
    first = res.parcels[0].trajectory.events[0]
    assert ev.t.iloc[0] == first.t and list(ev.entered.iloc[0]) == list(first.entered)
    # the CSV says the same, to the last bit
    rows = list(csv.DictReader(open(paths["trajectories.csv"])))
    assert len(rows) == len(traj)
    assert all(float(r["x"]) == x for r, x in zip(rows, traj.x))
    ev_rows = list(csv.DictReader(open(paths["events.csv"])))
    assert [int(i) for i in ev_rows[0]["entered"].split()] == list(first.entered)


def test_cell_table_matches_the_network_totals_and_the_sensors(tmp_path):
    res = run(_recorded().build())
    paths = io.write_results(res, tmp_path, formats=("parquet",))
    cells = pd.read_parquet(paths["cells"])
    net = pd.read_parquet(paths["network"])
    n = res.setup.cells.n
    assert len(cells) == len(net) * n
    assert np.array_equal(cells.groupby("t").sent.sum().to_numpy(), net.sent.to_numpy())
    assert np.array_equal(cells.groupby("t").received.sum().to_numpy(), net.received.to_numpy())
    traffic = pd.read_parquet(paths["cell_traffic"])
    assert np.array_equal(cells.groupby("cell").sent.sum().to_numpy(), traffic.sent.to_numpy())
    assert cells.s0.dtype == bool and cells.s0.any() and not cells.s0.all()
    assert net.latency_mean.isna().sum() == np.isnan(res.network.per_tick["latency_mean"]).sum()
    assert not (tmp_path / "cells.csv").exists()


def test_run_folder_reproduces_a_scenario_built_in_code(tmp_path):
    """A scenario made in Python (no file) is written out as TOML; running that file gives the same tables."""
    sc = load_scenario("crossing_30x30")[0]
    sc = sc.model_copy(update={"name": "made_in_code", "duration": 2.0,
                               "parcels": [sc.parcels[0].model_copy(update={"x": sc.parcels[0].x + 0.013})]})
    res = run(sc.build())
    first = tmp_path / "first"
    io.write_results(res, first)
    assert parse_text((first / "scenario.toml").read_text()) == sc
    again = tmp_path / "again"
    out = CliRunner().invoke(app, ["run", str(first / "scenario.toml"), "-o", str(again), "--no-plot"])
    assert out.exit_code == 0, out.output
    for name in ("trajectories.parquet", "events.parquet"):
        assert pq.read_table(first / name).equals(pq.read_table(again / name))
    manifest = json.loads((again / "run.json").read_text())
    assert manifest["scenario"] == "made_in_code" and manifest["seeds"] == {"sensors": 0}
    for name, entry in manifest["files"].items():
        data = (again / name).read_bytes()
        assert entry == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    assert "run.json" not in manifest["files"] and "trajectories.csv" in manifest["files"]


def test_every_bundled_scenario_survives_a_trip_through_toml():
    from virtual_vehicle.config.scenario import bundled_scenarios

    for name in bundled_scenarios():
        sc = load_scenario(name)[0]
        assert parse_text(dump_toml(sc)) == sc, name


def test_format_option_is_checked(tmp_path):
    out = CliRunner().invoke(app, ["run", "paper_2x2_inward", "-o", str(tmp_path), "--format", "xlsx"])
    assert out.exit_code == 2 and "--format" in out.output and "parquet" in out.output
    out = CliRunner().invoke(app, ["run", "paper_2x2_inward", "-o", str(tmp_path), "--format", "csv",
                                   "--no-plot"])
    assert out.exit_code == 0 and (tmp_path / "trajectories.csv").exists()
    assert not (tmp_path / "trajectories.parquet").exists()
    with pytest.raises(ValueError, match="formats"):
        io.write_results(run(load_scenario("paper_2x2_inward")[0].build()), tmp_path, formats=("xls",))


def test_tables_of_a_run_without_events_are_empty_not_missing():
    res = run(load_scenario("paper_2x2_inward")[0].build())
    t = tables.build(res)
    assert t["events"].num_rows == sum(len(p.trajectory.events) for p in res.parcels)
    assert t["events"].schema.field("t").metadata[b"unit"] == b"s"
