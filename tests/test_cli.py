"""The command and scenario files: bundled scenarios run, results are written, bad input is one clear error with
exit code 2 and no traceback."""

import csv
import json
import re
import subprocess
import sys
import tomllib
from importlib import resources

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from virtual_vehicle.config.scenario import bundled_scenarios, load_scenario, parse_scenario, parse_text
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run
from virtual_vehicle.ui.cli import app

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


def test_a_run_compiles_first_and_says_so_where_these_sources_have_no_compiled_code(tmp_path, monkeypatch):
    """Where the cache folder for this checkout's sources holds no compiled code (the first run after they changed),
    `run` compiles the engine before it builds and times the run, saying so; where it holds some, it loads it
    (silently) before the run just as well, so that the run's wall time is the simulation's."""
    import virtual_vehicle.run.warm as warm

    calls = []
    monkeypatch.setattr(warm, "warm_up", lambda: calls.append(1) or 0.0)
    empty = tmp_path / "numba-new"
    empty.mkdir()
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(empty))
    result = runner.invoke(app, ["run", "--out", str(tmp_path / "a"), "--no-plot"])
    assert result.exit_code == 0, result.output
    assert calls == [1, 1] and "compiling the event engine" in result.output  # compiled, then loaded (at once)
    (empty / "engine_x").mkdir()
    (empty / "engine_x" / "_kernel.f-1.py311.nbi").write_bytes(b"")
    result = runner.invoke(app, ["run", "--out", str(tmp_path / "b"), "--no-plot"])
    assert result.exit_code == 0, result.output
    assert calls == [1, 1, 1] and "compiling" not in result.output and "loading" not in result.output


def test_a_bad_scenario_fails_before_the_engine_is_loaded(tmp_path, monkeypatch):
    """An invalid scenario is refused as it is built, before a second is spent loading the compiled engine, and
    the error is the one line on stderr."""
    import virtual_vehicle.run.warm as warm

    calls = []
    monkeypatch.setattr(warm, "warm_up", lambda: calls.append(1) or 0.0)
    from virtual_vehicle.config.scenario import load_scenario

    path = tmp_path / "coarse.toml"
    path.write_text(load_scenario("prototype_18")[1] + '\n[integrator]\nmode = "fixed"\ndt = 0.5\n')
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "integrator.dt" in result.output, result.output
    assert calls == []


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
    proc = subprocess.run([sys.executable, "-m", "virtual_vehicle.ui.cli", "run", str(p)], capture_output=True, text=True)
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
    for entry in resources.files("virtual_vehicle.config.scenarios").iterdir():
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            assert data["description"].strip()
            parse_text(entry.read_text())


def test_progress_bar_appears_only_after_its_delay():
    from virtual_vehicle.ui.cli import LazyProgress

    quick = LazyProgress("x", delay=3600.0)
    quick(0.5)
    assert quick.bar is None  # a short run shows nothing
    slow = LazyProgress("x", delay=0.0)
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


def _prototype(**integrator) -> str:
    """The prototype's TOML with an [integrator] table (its bound: pitch 0.08 m / (10 x 0.5 m/s) = 0.016 s)."""
    text = load_scenario("prototype_18")[1]
    table = "\n".join(f"{k} = {_val(v)}" for k, v in integrator.items())
    return text.replace("[friction]", f"[integrator]\n{table}\n\n[friction]")


@pytest.mark.parametrize("dt", [0.5, 10.0, 0.0161, 0.05])
def test_a_fixed_step_that_cannot_resolve_the_scene_is_rejected_with_its_bound(dt):
    """dt = 0.5 s once "tipped at t=0 s" (an RK4 stage put the box half a metre off its cells) and exited 0."""
    sc = parse_text(_prototype(mode="fixed", dt=dt).replace("output_dt = 0.01", "output_dt = 0.5"))
    with pytest.raises(ScenarioError, match=r"integrator\.dt: .* at most pitch / \(10 x speed\) = 0\.016 s") as e:
        sc.build()
    assert e.value.field == "integrator.dt"


def test_a_fixed_step_within_its_bound_tracks_the_event_driven_run():
    """At the bound (dt = 0.016 s, one step per tenth of a cell at the fastest wheel) the fixed step keeps every
    support change of the event-driven run and stays within 2 mm of it (measured: 1.3 mm; 5x the bound drops support
    changes, 10x is wrong by 7 cm)."""
    event = run(load_scenario("prototype_18")[0].build()).parcels[0].trajectory
    text = _prototype(mode="fixed", dt=0.016).replace("output_dt = 0.01", "output_dt = 0.016")
    fixed = run(parse_text(text).build()).parcels[0].trajectory
    assert fixed.status == "completed"
    assert sum(e.kind == "support" for e in fixed.events) == sum(e.kind == "support" for e in event.events)
    assert np.max(np.abs(fixed.states[:, 0] - np.interp(fixed.times, event.times, event.states[:, 0]))) < 2e-3


def test_a_fixed_step_longer_than_the_output_spacing_is_rejected():
    sc = parse_text(_prototype(mode="fixed", dt=0.012))  # within the crossing bound, above output_dt = 0.01
    with pytest.raises(ScenarioError, match=r"integrator\.dt: 0\.012 s is longer than the output spacing"):
        sc.build()
    parse_text(_prototype(dt=0.012)).build()  # event mode samples its own dense output: fine


def test_the_step_bound_counts_the_programs_speed_and_the_parcels_own():
    d = base()  # uniform 0.2 m/s on a 0.1 m pitch: dt <= 0.05 s
    d["integrator"] = {"dt": 0.05}
    parse_scenario(d).build()
    d["parcels"][0]["vx"] = 1.0  # thrown on at 1 m/s: dt <= 0.01 s
    with pytest.raises(ScenarioError, match=r"\(1 m/s\)"):
        parse_scenario(d).build()


SORT = """
name = "small_sort"
duration = 0.5
output_dt = 0.05
[array]
kind = "map"
pitch = 0.1
map = \"\"\"
....11....
....oo....
EEoooooo00
EEoooooo00
..oooooo00
\"\"\"
[control]
program = "sort"
speed = 0.3
[[parcels]]
name = "p"
length = 0.18
width = 0.16
mass = 1.0
mu = 0.5
x = 0.05
y = 0.15
destination = 1
"""
SORT_COULOMB = SORT + '[friction]\nlaw = "coulomb"\n'  # named: the default is stick-slip


def test_networked_coulomb_runs_check_sliding_and_the_cli_warns(tmp_path):
    """A sorter on the paper's Coulomb law: the parcel outruns its 0.3 m/s wheels; networked runs used to skip the
    check (coulomb_sliding_checked false) and print no warning. Under the viscous law and the default stick-slip
    law there is nothing to check and no warning."""
    path = tmp_path / "small_sort.toml"
    path.write_text(SORT_COULOMB)
    result = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "o"), "--no-plot"])
    assert result.exit_code == 0, result.output
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    p = s["parcels"][0]
    assert p["coulomb_sliding_checked"] and p["coulomb_sliding_assumption_violated_at_s"] is not None
    assert p["coulomb_max_reversed_slip_m_per_s"] > 0.05
    assert s["coulomb_sliding"]["checked"] and s["coulomb_sliding"]["parcels_violating"] == 1
    assert "warning: the Coulomb law's assumption" in result.stderr and '[friction] law = "viscous"' in result.stderr
    said = result.stdout + result.stderr  # said once, naming the parcel (its own line used to repeat it)
    assert said.count("outran a wheel") == 1 and said.count("viscous") == 1
    named = re.search(r"\(p from t=([0-9.]+) s\)", result.stderr)  # the parcel and when, as the summary has it
    assert named and abs(float(named.group(1)) - p["coulomb_sliding_assumption_violated_at_s"]) < 0.05
    for law, text in (("viscous", SORT + '[friction]\nlaw = "viscous"\n'), ("stick_slip", SORT)):
        path.write_text(text)
        other = runner.invoke(app, ["run", str(path), "--out", str(tmp_path / law), "--no-plot"])
        assert other.exit_code == 0 and "warning" not in other.stderr
        s = json.loads((tmp_path / law / "summary.json").read_text())
        assert s["friction_law"] == law and not s["coulomb_sliding"]["checked"]


def test_a_reused_run_folder_holds_exactly_the_new_runs_files(tmp_path):
    """A prototype run into the folder of a networked run with pictures used to keep network.*, traffic.png and
    paths.png beside its own files."""
    out = tmp_path / "o"
    out.mkdir()
    earlier = ["run.json", "summary.json", "network.csv", "network.parquet", "cell_traffic.csv", "traffic.png",
               "paths.png", "cells.parquet", ".trajectories.csv.abc123"]
    for name in earlier:
        (out / name).write_text("earlier run")
    (out / "my_notes.txt").write_text("mine")
    p = _write(tmp_path, BASE)
    result = runner.invoke(app, ["run", str(p), "--out", str(out), "--no-plot", "--format", "csv"])
    assert result.exit_code == 0, result.output
    names = {f.name for f in out.iterdir()}
    assert names == {"trajectories.csv", "events.csv", "summary.json", "scenario.toml", "run.json", "my_notes.txt"}
    assert set(json.loads((out / "run.json").read_text())["files"]) == names - {"run.json", "my_notes.txt"}


def test_a_foreign_folder_or_a_file_as_out_is_refused_before_running(tmp_path):
    p = _write(tmp_path, BASE)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("mine")
    r = runner.invoke(app, ["run", str(p), "--out", str(foreign)])
    assert r.exit_code == 2 and "thesis.tex" in r.stderr and "no run.json" in r.stderr
    assert {f.name for f in foreign.iterdir()} == {"thesis.tex"}
    unfinished = tmp_path / "unfinished"  # an interrupted run's files (no manifest yet) are ours to replace
    unfinished.mkdir()
    (unfinished / "trajectories.csv").write_text("half")
    (unfinished / "ckpt.bin").write_text("a checkpoint")
    r = runner.invoke(app, ["run", str(p), "--out", str(unfinished), "--no-plot", "--checkpoint",
                            str(unfinished / "ckpt.bin")])
    assert r.exit_code == 0, r.output
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out in (afile, afile / "sub"):
        r = runner.invoke(app, ["run", str(p), "--out", str(out)])
        assert r.exit_code == 2 and "is a file" in r.stderr and "summary" not in r.output


def test_compare_keeps_an_earlier_comparison_unless_forced(tmp_path):
    out = tmp_path / "cmp"
    out.mkdir()
    (out / "compare.json").write_text("{}")
    r = runner.invoke(app, ["compare", "pose_tasks", "--out", str(out)])
    assert r.exit_code == 2 and "--force" in r.stderr and "Traceback" not in r.output
    assert (out / "compare.json").read_text() == "{}"


def test_huge_runs_are_refused_with_the_estimate_before_allocating():
    d = base()
    d.update(duration=1e6, output_dt=1e-6)
    with pytest.raises(ScenarioError, match=r"output_dt: this run would hold about .* TiB in memory .* more than "
                                            r"the limit of"):
        parse_scenario(d).build()
    d.update(duration=1e6, output_dt=1.0)  # a long run sampled sparsely is fine
    parse_scenario(d).build()


def test_memory_estimate_counts_ticks_and_recorded_cells():
    from virtual_vehicle.config.scenario import memory_estimate

    sc = load_scenario("prototype_18_network_ideal")[0]
    sc = sc.model_copy(update={"duration": 1e3, "sensors": sc.sensors.model_copy(update={"record": True})})
    est = memory_estimate(sc.build())
    ticks = 1e3 / sc.control.period
    assert est["control.period"] == ticks * 96 and est["sensors.record"] == ticks * 18 * (5 + 48)


def test_physically_meaningless_sizes_are_rejected_naming_the_field():
    for path, value, field in [(("parcels", 0, "mass"), 1e-300, "parcels[0].mass: must be at least 1e-12"),
                               (("parcels", 0, "length"), 1e-300, "parcels[0].length: must be at least 1e-09"),
                               (("array", "pitch"), 1e-12, "array.pitch: must be at least 1e-09"),
                               (("parcels", 0, "inertia"), 1e-300, "parcels[0].inertia")]:
        with pytest.raises(ScenarioError, match=re.escape(field)):
            parse_scenario(_mutate(path, value))


def test_a_directory_is_not_taken_for_a_missing_scenario(tmp_path):
    folder = tmp_path / "17_dir.toml"
    folder.mkdir()
    r = runner.invoke(app, ["check", str(folder)])
    assert r.exit_code == 2 and "is a directory" in r.stderr and "no scenario file" not in r.stderr


def test_help_keeps_its_brackets_and_version_is_printed():
    r = runner.invoke(app, ["scale-study", "--help"])
    assert "[field]" in r.output
    r = runner.invoke(app, ["animate", "--help"])
    assert "[sensors] record = true" in r.output
    r = runner.invoke(app, ["--version"])
    from virtual_vehicle import __version__

    assert r.exit_code == 0 and r.output.strip() == f"virtual-vehicle {__version__}"


def test_a_long_phase_shows_a_status_line(capsys):
    from virtual_vehicle.ui.cli import Phase

    with Phase("building a huge array", delay=0.0):
        pass
    with Phase("reading", delay=3600.0):  # a short phase shows nothing
        pass
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "building a huge array ..." and lines[1].startswith("building a huge array: done in ")
    assert len(lines) == 2
