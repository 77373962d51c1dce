"""Where a tick of the sorter hall goes (issue 32 item 6): the 200-parcel, 10^4-cell, 100 Hz hall of
``bench_scale.py`` on the stick-slip law, its phases timed by wrapping their entry points (no profiler, whose
overhead per call would favour the compiled parts). Prints each phase's wall time, calls and time per call of the
fastest of ``--runs`` runs; asserts nothing about time. Nested phases are indented; they overlap their parents.

Run: ``python benchmarks/hall_phases.py --seconds 1 --runs 2``; ``--per-second`` also prints each simulated second's
wall time and its cells' part (the hall does not settle: its parcels start, travel and queue at the one exit).
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_scale  # noqa: E402

from virtual_vehicle.config.scenario import parse_scenario  # noqa: E402
from virtual_vehicle.engine import glide, plant, ride  # noqa: E402
from virtual_vehicle.run import sim  # noqa: E402
from virtual_vehicle.run.warm import warm_up  # noqa: E402

TOTAL: collections.Counter = collections.Counter()
CALLS: collections.Counter = collections.Counter()


def timed(owner, name: str, label: str) -> None:
    """Replace ``owner.name`` by itself timed under ``label``."""
    inner = getattr(owner, name)

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            TOTAL[label] += time.perf_counter() - start
            CALLS[label] += 1

    setattr(owner, name, wrapper)


PHASES = [(sim.NetworkRun, "tick", "tick"),
          (sim.NetworkRun, "_decide", "  sorter and network"),
          (sim.TickedRun, "finish", "  plant and tracks"),
          (plant.Plant, "plan", "    plan"),
          (ride.RideStepper, "step", "    ride step"),
          (ride.RideStepper, "_measure_known", "      compiled measure"),
          (ride.RideStepper, "measure", "      anchors made in Python"),
          (ride.RideStepper, "_ride_data", "      ride data in Python"),
          (ride.RideStepper, "_riding", "      proof"),
          (ride, "rigid_motion", "      closed form"),
          (glide.GlideStepper, "step", "    glide step (translating over a uniform field)"),
          (plant, "integrate_prechecked", "    exact path (windows not riding)"),
          (sim.ParcelTrack, "add_quiet", "    tracks: blocks"),
          (sim.ParcelTrack, "add", "    tracks: trajectories")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated seconds (default 1)")
    ap.add_argument("--runs", type=int, default=2, help="runs; the fastest is printed (default 2)")
    ap.add_argument("--per-second", action="store_true", help="print each simulated second's wall time (fastest run)")
    args = ap.parse_args()
    for owner, name, label in PHASES:
        timed(owner, name, label)
    setup = parse_scenario(bench_scale.scenario(100, 200, args.seconds, law="stick_slip")).build()
    warm_up()
    best = None
    for _ in range(args.runs):
        TOTAL.clear()
        CALLS.clear()
        job = sim.NetworkRun(setup)
        seconds = []  # per simulated second: (wall, the cells' part) in s
        start = time.perf_counter()
        while not job.done:
            job.tick()
            if job.k * job.period >= len(seconds) + 1 - 1e-9 or job.done:
                seconds.append((time.perf_counter() - start - sum(w for w, _ in seconds),
                                TOTAL["  sorter and network"] - sum(c for _, c in seconds)))
        res = job.result()
        wall = time.perf_counter() - start
        if best is None or wall < best[0]:
            g = job.plant._glide
            reasons = {} if g is None else {r: int(c) for r, c in zip(glide.REASONS, g.reasons) if c}
            best = wall, dict(TOTAL), dict(CALLS), res.stats["plant"]["quiet_steps"], reasons, seconds
    wall, total, calls, rides, reasons, seconds = best
    print(f"# {wall:.3f} s wall for {args.seconds} s simulated; {rides} parcel windows rode")
    for _, _, label in PHASES:
        if calls.get(label):
            each = 1e6 * total[label] / calls[label]
            print(f"{label:36s} {total[label]:8.3f} s {calls[label]:8d} calls {each:10.1f} us a call")
    print("# glide: parcel windows written in closed form, and why the others went on to the exact path:", reasons)
    if args.per_second:
        for k, (w, cells) in enumerate(seconds):
            print(f"second {k + 1}: {w:6.2f} s wall, of it the sorter and network {cells:6.2f} s")


if __name__ == "__main__":
    main()
