"""The benchmarks measure what they say (issue 8): their single-parcel runs last the whole simulated time they divide
by, and the Coulomb one stays within the paper's sliding assumption. (A parcel that tipped off the array after 0.7 s
was once reported as 5 s of motion.) Nothing here looks at wall time."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.run.sim import coulomb_sliding_check

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_engine  # noqa: E402
import bench_perf  # noqa: E402


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("law", ["coulomb", "viscous"])
def test_the_event_versus_fixed_benchmark_runs_its_whole_time(law):
    """bench_perf (b): the parcel stays on the array for the 5 s and crosses cells all along (Coulomb: it
    oscillates about the centre, hundreds of support changes); under Coulomb its wheels outrun it at every sample.
    The first trial step spans the whole 5 s and overflows under the viscous law: the error control rejects it,
    and nothing is printed."""
    velocities = bench_perf.FIELDS_B[law]
    model = ParcelModel(bench_perf.CELLS, bench_perf.SPEC, velocities, bench_perf.LAWS[law])
    tr = integrate(model, bench_perf.Y0_IN, 0.0, 5.0, sample_dt=0.01)
    assert tr.status == "completed" and tr.t_end == 5.0
    changes = sum(e.kind == "support" for e in tr.events)
    assert changes > (400 if law == "coulomb" else 20)
    if law == "coulomb":
        setup = SimpleNamespace(contact_layer=bench_perf.CELLS, contact_velocities=velocities)
        assert coulomb_sliding_check(setup, bench_perf.SPEC, tr) is None
        # and the same parcel on the uniform field of (a) would not last: it is what (b) must not use
        uniform = ParcelModel(bench_perf.CELLS, bench_perf.SPEC, bench_perf.V, bench_perf.LAWS[law])
        assert integrate(uniform, bench_perf.Y0, 0.0, 5.0, sample_dt=5.0).status == "tipped"


def test_the_engine_benchmark_crossing_completes():
    """bench_engine: the viscous crossing, at both headings, runs the 5 s it reports and crosses cells."""
    for heading in (0.0, 0.3):
        _, tr = bench_engine.crossing("event", heading)
        assert tr.status == "completed" and tr.t_end == 5.0
        assert len(tr.events) > 20


def test_the_scale_benchmark_reports_the_cells_it_stepped():
    """bench_scale: by default the sorter is stepped on some of the cells, with --every-cell on all of them, and the
    figures are for the time asked for (that both give the same run is tested in test_changed_cells)."""
    import bench_scale

    some = bench_scale.one(30, 1, 0.3)
    every = bench_scale.one(30, 1, 0.3, changed_only=False)
    assert 0 < some["cells_stepped_%"] < 50 and every["cells_stepped_%"] == 100
    assert some["simulated_s"] == every["simulated_s"] == 0.3 and some["cells"] == 900


def test_the_ceiling_benchmark_times_every_piece_and_puts_the_kernels_back():
    """bench_ceiling: within ``timed_kernels`` every module holding the engine's compiled entry point holds the
    timing wrapper, which counts one call per hand-back to Python (the event loop runs many pieces a call: fewer
    calls than pieces, a run without a progress callback never pausing); the originals
    are back afterwards, and a run's figures are ordered as they must be (work within the calls within the wall)."""
    import bench_ceiling
    from numba.core.registry import CPUDispatcher

    from virtual_vehicle.engine import _kernel

    original = _kernel.run_events
    model = ParcelModel(bench_perf.CELLS, bench_perf.SPEC, bench_perf.FIELDS_B["coulomb"], bench_perf.LAWS["coulomb"])
    with bench_ceiling.timed_kernels() as stats:
        assert _kernel.run_events is not original and _kernel.run_events.__wrapped__ is original
        tr = integrate(model, bench_perf.Y0_IN, 0.0, 0.5, sample_dt=0.5)
    assert _kernel.run_events is original
    assert not [(mod.__name__, name) for mod in bench_ceiling.package_modules() for name, obj in vars(mod).items()
                if callable(obj) and hasattr(obj, "__wrapped__") and isinstance(obj.__wrapped__, CPUDispatcher)]
    entry = stats["virtual_vehicle.engine._kernel.run_events"]
    assert 0 < entry.calls < tr.segments and tr.segments > 20 and entry.seconds > 0
    # the restart and probe states, the cells under the probe, the candidates' ids, positions and centre
    assert bench_ceiling.arrays_in(entry.result) == 6
    assert bench_ceiling.arrays_in((np.zeros(2), (1.0, np.zeros(1)), 3, [np.zeros(1)])) == 2
    assert bench_ceiling.call_price(entry) > 3 * bench_ceiling.array_return_price() > 0

    r = bench_ceiling.run_case("coulomb1", 0.5)
    assert r["simulated"] == 0.5 and 0 < r["work"] <= r["inside"] < r["wall"]
    assert r["calls"] == sum(k[1] for k in r["kernels"])
    assert "virtual_vehicle.engine._kernel.run_events" in {k[0] for k in r["kernels"]}
    with pytest.raises(ValueError, match="unknown case"):
        bench_ceiling.run_case("coulomb2")


def test_a_call_s_price_is_its_arguments_in_and_each_array_out(monkeypatch):
    """bench_ceiling.call_price: the do-nothing call with the entry's arguments plus the price of returning one array
    for each array in its result (timings replaced by fixed figures, so that the sum is exact)."""
    import bench_ceiling

    monkeypatch.setattr(bench_ceiling, "_fastest", lambda fn, args, repeats: 1e-6 * (1 + len(args)))
    monkeypatch.setattr(bench_ceiling, "array_return_price", lambda: 0.25e-6)
    entry = bench_ceiling.EntryPoint(calls=1, args=(1.0, np.zeros(3)), kwargs={"k": 2},
                                     result=(np.zeros(2), 3.0, (np.zeros(1), np.zeros(1))))
    assert bench_ceiling.call_price(entry) == 4e-6 + 3 * 0.25e-6
    assert bench_ceiling.call_price(bench_ceiling.EntryPoint(result=7)) == 1e-6


@pytest.mark.parametrize("law", ["viscous", "coulomb"])
def test_the_pairs_benchmark_runs_its_whole_time_within_the_laws_assumptions(law):
    """bench_pairs: every parcel runs the whole time reported, none overlaps another unnoticed, and under the
    Coulomb law every parcel stays slower than its wheels (the paper's sliding assumption) for the 1.5 s the
    benchmark allows."""
    import bench_pairs

    r = bench_pairs.one(25, law, 1.5)
    assert r["whole_time"] == 25 and r["undetected_overlaps"] == 0
    assert r["sliding_kept"] == 25


def test_the_dead_cell_stream_study_counts_what_a_plain_run_of_its_stream_delivers(tmp_path, capsys, monkeypatch):
    """fault_stream: the stream it writes feeds the junction a parcel every 3 s and loads as a scenario; its
    fault-free figure is what a plain run of that file delivers, and each rate's row names its draws' deliveries."""
    import fault_stream

    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import run
    from virtual_vehicle.run.tasks import sorting_report

    free = fault_stream.stream_file(0.25, tmp_path / "free", dead_wheels="free")
    assert load_scenario(free)[0].faults.dead_wheels == "free"
    path = fault_stream.stream_file(0.25, tmp_path)
    sc, _ = load_scenario(path)
    assert sc.faults.dead_wheels == "held"
    assert sc.duration == 15.0 and [p.t_start for p in sc.parcels] == [3.0 * k for k in range(5)]
    plain = sum(r["outcome"] == "delivered" and r["correct"] for r in sorting_report(run(sc.build()))["parcels"])
    assert plain >= 1  # (the first parcel leaves the junction at ~8.6 s)
    monkeypatch.setattr(sys, "argv", ["fault_stream", "--minutes", "0.25", "--rates", "0.1", "--samples", "2",
                                      "--workers", "1", "--out", str(tmp_path)])
    fault_stream.main()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split("fault-free ")[1].startswith(f"{plain} delivered")
    row = lines[-1].split()  # rate, draws, cut off, share of the fault-free, 3 means, each seed's deliveries
    assert row[:3] == ["0.10", "2", "0"] and len(row) == 9
    seeds = [int(k) for k in row[-2:]]
    assert all(0 <= k <= len(sc.parcels) for k in seeds)
    assert abs(float(row[3].rstrip("%")) - 100 * sum(seeds) / 2 / plain) < 0.06


def test_the_clocks_benchmark_measures_how_long_a_sentence_waits_for_its_reader():
    """bench_clocks' mailbox watch: on one shared clock (the synchronous run) it counts nothing (a sentence is read
    a period after it was sent, by the model's definition); on own clocks every sentence read waited at least one
    grid instant and at most a period of the slowest clock plus the jitter, and with the ticks spread over the
    period the mean is well under a period (the reader ticks within a period of the sender, before or after it)."""
    import bench_clocks

    from virtual_vehicle.config.scenario import load_scenario

    sc, _ = load_scenario("sorting_junction")
    sc = sc.model_copy(update={"duration": 1.0})
    _, _, _, sync = bench_clocks.delivered(sc, {})
    assert sync.read == 0 and sync.mean() is None
    drift, jitter, period = 0.01, 0.001, sc.control.period
    _, _, _, own = bench_clocks.delivered(sc, {"drift": drift, "jitter": jitter, "seed": 1})
    assert own.read > 1000 and own.put >= own.read
    assert period / 20 - 1e-12 <= own.shortest and own.longest <= period * (1 + drift) + jitter + period / 20
    assert 0.3 * period < own.mean() < 0.7 * period


def test_the_hall_phases_benchmark_splits_its_run_by_simulated_second():
    """hall_phases --per-second: a line for each simulated second begun (one for a run shorter than a second), whose
    cells' part lies within it and whose wall time lies within the run's. In its own process: the script wraps the
    run's classes for good."""
    import re
    import subprocess

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "hall_phases.py"
    out = subprocess.run([sys.executable, str(script), "--seconds", "0.05", "--runs", "1", "--per-second"],
                         capture_output=True, text=True, check=True).stdout
    total = float(re.search(r"^# ([0-9.]+) s wall for 0.05 s simulated", out, re.M).group(1))
    seconds = re.findall(r"^second (\d+): +([0-9.]+) s wall, of it the sorter and network +([0-9.]+) s$", out, re.M)
    assert [k for k, _, _ in seconds] == ["1"]
    wall, cells = float(seconds[0][1]), float(seconds[0][2])
    assert 0 < cells <= wall <= total + 0.01
