"""The command and scenario files: bundled scenarios run, results are written, bad input is one clear error with
exit code 2 and no traceback."""

import csv
import json
import subprocess
import sys
import tomllib
from importlib import resources

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from virtual_vehicle.cli import app
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.scenario import bundled_scenarios, load_scenario, parse_scenario, parse_text
from virtual_vehicle.sim import run

runner = CliRunner()

BASE = """
name = "t"
duration = 0.5
[array]
kind = "grid"
nx = 5
ny = 4
pitch = 0.1
[field]
kind = "uniform"
velocity = [0.2, 0.0]
[friction]
law = "viscous"
[[parcels]]
name = "a"
length = 0.25
width = 0.2
mass = 1.0
mu = 1.0
x = 0.15
y = 0.15
"""


def base() -> dict:
    return tomllib.loads(BASE)


@pytest.mark.parametrize("name", sorted(bundled_scenarios()))
def test_bundled_scenarios_run(name, tmp_path):
    result = runner.invoke(app, ["run", name, "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    for f in ("trajectories.csv", "events.csv", "summary.json", "scenario.toml", "paths.png"):
        assert (tmp_path / f).stat().st_size > 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["scenario"] == name
    for p in summary["parcels"]:
        if "outcome" in p:  # a sorting run: parcels leave through their exits
            assert p["outcome"] in ("on_array", "waiting") or (p["outcome"] == "delivered" and p["correct"]), p
            continue
        assert p["status"] == "completed", f"{name}: {p['name']} should stay on the array"
        assert p["coulomb_sliding_assumption_violated_at_s"] is None, f"{name}: wheels too slow for the paper's law"
    rows = list(csv.DictReader(open(tmp_path / "trajectories.csv")))
    assert list(rows[0]) == ["parcel", "t", "x", "y", "theta", "vx", "vy", "omega"]
    assert max(float(r["t"]) for r in rows) == pytest.approx(summary["duration_s"])
    assert all(np.isfinite(float(r[k])) for r in rows for k in ("x", "y", "theta", "vx", "vy", "omega"))


def test_prototype_passes_the_box_back_and_forth():
    sc, _ = load_scenario("prototype_18")
    tr = run(sc.build()).parcels[0].trajectory
    vx = tr.states[:, 3]
    reversals = np.count_nonzero(np.sign(vx[1:]) * np.sign(vx[:-1]) < 0)
    assert reversals >= 8 and tr.status == "completed"
    assert sum(e.kind == "support" for e in tr.events) >= 10


def test_row_oscillator_changes_supports_and_stays_on():
    sc, _ = load_scenario("row_oscillator")
    tr = run(sc.build()).parcels[0].trajectory
    assert tr.status == "completed" and len(tr.events) >= 10


def test_default_run_names_its_folder(tmp_path):
    result = runner.invoke(app, ["run", "--out", str(tmp_path / "d")])
    assert result.exit_code == 0, result.output
    assert "results written to" in result.output and (tmp_path / "d" / "paths.png").exists()


def test_scenarios_and_check_commands():
    r = runner.invoke(app, ["scenarios"])
    assert r.exit_code == 0 and "prototype_18 (default)" in r.output
    r = runner.invoke(app, ["check", "row_oscillator"])
    assert r.exit_code == 0 and "valid" in r.output


def _write(tmp_path, data_or_text):
    p = tmp_path / "s.toml"
    if isinstance(data_or_text, str):
        p.write_text(data_or_text)
    else:
        lines = []
        _dump(data_or_text, lines)
        p.write_text("\n".join(lines))
    return p


def _val(v):
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_val(x) for x in v) + "]"
    return repr(v)


def _dump(data, lines, prefix=""):
    """A tiny TOML writer for the tests (scalars, arrays, tables, arrays of tables)."""
    for k, v in data.items():
        if not isinstance(v, (dict, list)) or (isinstance(v, list) and not (v and isinstance(v[0], dict))):
            lines.append(f"{k} = {_val(v)}")
    for k, v in data.items():
        if isinstance(v, dict):
            lines.append(f"[{prefix}{k}]")
            _dump(v, lines, prefix=f"{prefix}{k}.")
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                lines.append(f"[[{prefix}{k}]]")
                _dump(item, lines, prefix=f"{prefix}{k}.")


def _mutate(path, value):
    d = base()
    node = d
    for p in path[:-1]:
        node = node[p]
    if value is _DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


_DELETE = object()

BAD = [
    (("parcels", 0, "mass"), -1.0, "parcels[0].mass"),
    (("parcels", 0, "length"), 0.0, "parcels[0].length"),
    (("friction", "law"), "rubber", "friction.law"),
    (("parcels", 0, "x"), 5.0, "parcels[0].x"),
    (("parcels", 0, "color"), "red", "parcels[0].color"),
    (("duration",), -2.0, "duration"),
    (("duration",), _DELETE, "duration"),
    (("array", "pitch"), 0.0, "array.pitch"),
    (("array", "kind"), "hexagon", "array"),
    (("field", "velocity"), [0.1], "field.velocity"),
    (("integrator",), {"mode": "leapfrog"}, "integrator.mode"),
    (("output_dt",), 10.0, "output_dt"),
    (("gravity",), float("nan"), "gravity"),
]


@pytest.mark.parametrize("path,value,field", BAD, ids=[b[2] + "-" + str(i) for i, b in enumerate(BAD)])
def test_bad_input_is_one_clear_error_naming_the_field(tmp_path, path, value, field):
    p = _write(tmp_path, _mutate(path, value))
    result = runner.invoke(app, ["run", str(p), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2, result.output
    assert field in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "o").exists()


def test_overlapping_parcels_and_wrong_per_cell_count(tmp_path):
    d = base()
    d["parcels"].append(dict(d["parcels"][0], name="b", x=0.2))
    with pytest.raises(ScenarioError, match=r"parcels\[1\].*overlaps"):
        parse_scenario(d).build()
    d = base()
    d["field"] = {"kind": "per_cell", "velocities": [[0.1, 0.0]] * 3}
    with pytest.raises(ScenarioError, match="one \\[vx, vy\\] per cell: 20 rows"):
        parse_scenario(d).build()
    d = base()
    d["parcels"].append(dict(d["parcels"][0]))
    with pytest.raises(ScenarioError, match="used twice"):
        parse_scenario(d)


def test_malformed_toml_and_missing_file(tmp_path):
    p = _write(tmp_path, "duration = = 3\n[array\n")
    r = runner.invoke(app, ["run", str(p)])
    assert r.exit_code == 2 and "not valid TOML" in r.output
    r = runner.invoke(app, ["run", str(tmp_path / "nope.toml")])
    assert r.exit_code == 2 and "no scenario file or bundled scenario" in r.output


def test_parcel_balanced_on_a_line_of_cells_is_rejected():
    d = base()
    d["parcels"][0].update(length=0.25, width=0.05, x=0.2, y=0.11)  # over row y=0.1 only, centre of mass off it
    with pytest.raises(ScenarioError, match="cannot rest"):
        parse_scenario(d).build()


def test_console_script_exit_code_without_traceback(tmp_path):
    p = _write(tmp_path, _mutate(("parcels", 0, "mass"), -3.0))
    proc = subprocess.run([sys.executable, "-m", "virtual_vehicle.cli", "run", str(p)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "parcels[0].mass" in proc.stderr and "Traceback" not in proc.stderr


scalar = st.one_of(st.none(), st.booleans(), st.integers(-10, 10), st.floats(allow_nan=True, allow_infinity=True),
                   st.text(max_size=5))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_random_malformed_scenarios_are_rejected_cleanly(data):
    """Replace or delete a random field of a valid scenario with junk: the result is either a valid scenario or a
    ScenarioError, never another exception."""
    d = base()
    paths = [("duration",), ("array", "nx"), ("array", "pitch"), ("array", "kind"), ("field", "velocity"),
             ("field", "kind"), ("friction", "law"), ("parcels", 0, "mass"), ("parcels", 0, "x"),
             ("parcels", 0, "width"), ("parcels", 0, "mu"), ("parcels",), ("integrator",), ("gravity",)]
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        node = d
        try:
            for p in path[:-1]:
                node = node[p]
        except (KeyError, IndexError, TypeError):
            continue
        if not isinstance(node, (dict, list)):
            continue
        if data.draw(st.booleans()):
            value = data.draw(scalar)
        else:
            value = data.draw(st.one_of(st.lists(scalar, max_size=3), st.dictionaries(st.text(max_size=4), scalar, max_size=2)))
        try:
            node[path[-1]] = value
        except (IndexError, TypeError):
            continue
    try:
        parse_scenario(d).build()
    except ScenarioError as exc:
        assert str(exc)


def test_bundled_files_are_valid_toml_with_descriptions():
    for entry in resources.files("virtual_vehicle.scenarios").iterdir():
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            assert data["description"].strip()
            parse_text(entry.read_text())


def test_progress_bar_appears_only_after_its_delay():
    from virtual_vehicle.cli import _LazyProgress

    quick = _LazyProgress("x", delay=3600.0)
    quick(0.5)
    assert quick.bar is None  # a short run shows nothing
    slow = _LazyProgress("x", delay=0.0)
    slow(0.25)
    slow(0.5)
    assert slow.bar is not None and slow.bar.tasks[0].completed == 0.5
    slow.close()


def test_compare_prints_pose_tasks_side_by_side(tmp_path):
    text = load_scenario("pose_tasks")[1].replace("duration = 8.0", "duration = 1.0")
    path = tmp_path / "short_pose_tasks.toml"
    path.write_text(text)
    result = runner.invoke(app, ["compare", str(path), "--out", str(tmp_path / "cmp")])
    assert result.exit_code == 0, result.output
    assert "largest final error (mm)" in result.output and "distributed" in result.output
    both = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert both["scenario"] == "pose_tasks"
    for mode in ("distributed", "central"):
        assert both[mode]["collisions"] == 0 and both[mode]["final_error_max_mm"] > 0
