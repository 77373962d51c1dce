"""Dead cells against throughput (issue 33: 5 % dead cells >= 95 % of the fault-free deliveries, 10 % >= 85 %).
Prints figures; asserts nothing.

The fault study on ``sorting_junction``'s own 40 s counts one parcel as 7.7 % of the fault-free run's 13, and that
run's 13th leaves 0.24 s before the cut: a draw whose parcels are a quarter of a second late loses it although it
delivers at the same rate. Here the junction is fed a parcel every 3 s (the stream of ``long_run.py``) for
``--minutes``, and the fault study (:func:`~virtual_vehicle.analysis.sweep.fault_study`, the same fault draws as
``virtual-vehicle fault-study``: fault seeds 0 .. samples - 1) runs on that stream: each rate's deliveries against
the fault-free run's, and the draws one by one. The stream's scenario is written beside the study
(``stream.toml``), so ``virtual-vehicle fault-study OUT/stream.toml`` reruns any of it.

``--dead-wheels free``: a dead cell's wheels turn with the parcel (``[faults] dead_wheels``) instead of holding it.

Run: ``python benchmarks/fault_stream.py [--minutes 3] [--rates 0.05 0.1] [--samples 20] [--dead-wheels held]
[--out DIR]`` (a 3-minute run takes ~70 s of one core; the fault-free run is made once, not once a seed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pyarrow.parquet as pq

from virtual_vehicle.analysis.sweep import fault_study
from virtual_vehicle.config.scenario import dump_toml

KIND = "dead_cell_rate"


def stream_file(minutes: float, out: Path, interval: float = 3.0, dead_wheels: str = "held") -> Path:
    """Write the junction's stream (a parcel every ``interval`` s for ``minutes``; a dead cell's wheels
    ``dead_wheels``) as ``out/stream.toml``."""
    from long_run import hour_scenario  # (this folder's: the junction's stream)

    out.mkdir(parents=True, exist_ok=True)
    path = out / "stream.toml"
    sc = hour_scenario(minutes, interval)
    sc = sc.model_copy(update={"faults": sc.faults.model_copy(update={"dead_wheels": dead_wheels})})
    path.write_text(dump_toml(sc), encoding="utf-8")
    return path


def per_seed(folder: Path, rate: float) -> list[int]:
    """Parcels delivered to the right exit in each fault seed's run at ``rate`` (seed order; finished runs)."""
    rows = [r for r in pq.read_table(folder / "summary.parquet").to_pylist()
            if r[f"vary.faults.{KIND}"] == rate and r["status"] == "ok"]
    return [r["sorting.correct"] for r in sorted(rows, key=lambda r: r["vary.faults.seed"])]


def _mean(value) -> str:
    """A study row's mean (None where no run reported it: ``-``)."""
    return "-" if value is None else f"{value:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--rates", type=float, nargs="+", default=[0.05, 0.1])
    parser.add_argument("--samples", type=int, default=20, help="fault seeds per rate")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--dead-wheels", choices=("held", "free"), default="held",
                        help="what a dead cell's wheels do (the scenario's [faults] dead_wheels)")
    parser.add_argument("--out", default="results/fault_stream")
    args = parser.parse_args()
    out = Path(args.out)
    scenario = str(stream_file(args.minutes, out, dead_wheels=args.dead_wheels))
    base = fault_study(scenario, KIND, [0.0], 1, out / "fault_free", workers=args.workers)[0]
    rows = fault_study(scenario, KIND, args.rates, args.samples, out / "faults", workers=args.workers)
    free = per_seed(out / "fault_free", 0.0)[0]
    print(f"sorting_junction fed every 3 s for {args.minutes:g} min, dead cells' wheels {args.dead_wheels}: "
          f"fault-free {free} delivered "
          f"(fraction {base['delivered_fraction']:.3f})")
    print(f"{'rate':>6}{'draws':>7}{'cut off':>8}{'of free':>9}{'collisions':>11}{'misrouted':>10}"
          f"{'deadlocked':>11}  delivered per seed")
    for r in rows:  # (the study's means leave out draws that cut an exit off: ``cut off``)
        seeds = per_seed(out / "faults", r["rate"])
        share = (f"{r['delivered_fraction'] / base['delivered_fraction']:.1%}"
                 if r["delivered_fraction"] is not None and base["delivered_fraction"] else "-")
        print(f"{r['rate']:>6.2f}{r['runs']:>7}{r['unreachable']:>8}{share:>9}{_mean(r['collisions']):>11}"
              f"{_mean(r['misrouted']):>10}{_mean(r['deadlocked']):>11}  {' '.join(map(str, seeds))}")


if __name__ == "__main__":
    main()
