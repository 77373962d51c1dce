"""One hour of sorting (reliability issue): the sorting junction fed a parcel every 3 s for a simulated hour, run
with checkpoints, then checked for drift in its invariants. Prints figures; exits 1 if an invariant broke.

Invariants: no collisions, no overlap between separately integrated parcels, no misrouted or lost parcel, every
state finite, deliveries keep pace with arrivals (at most 5% still waiting at the entry at the end), and the same
seed gives the same result (the first 60 s are run twice and compared bit for bit).

Memory (issue 32: flat over a one-hour run): the process's resident set (MiB, ``/proc/self/statm``; where that
file is missing, the peak from ``resource``) at every tenth of the run, and its growth per simulated hour over the
last nine tenths (the first tenth loads the compiled code and fills the array). The run's own results (each parcel's
trajectory, kept for the report) grow with the parcels run; the printed figure is everything together.

Run: ``python benchmarks/long_run.py [--minutes 60] [--checkpoint FILE [--resume]]`` (about 15 min of wall time
for an hour: 10 minutes took 146 s at the sixth session's ffa58fa and 182 s at fd5a7d3, both with the test suite
running beside it; 35 min an hour before the sorter was stepped only on the cells that changed); ``--resume``
continues an interrupted run from its checkpoint (the wall time printed is then only the resumed part's).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time

import numpy as np


def hour_scenario(minutes: float, interval: float = 3.0):
    from virtual_vehicle.config.scenario import load_scenario

    sc, _ = load_scenario("sorting_junction")
    duration = 60.0 * minutes
    base = sc.parcels
    parcels = []
    for k in range(int(duration / interval)):
        p = base[k % len(base)]
        parcels.append(p.model_copy(update={"name": f"p{k:05d}", "t_start": interval * k, "destination": k % 3}))
    return sc.model_copy(update={"name": f"sorting_{minutes:g}min", "duration": duration, "output_dt": 0.5,
                                 "parcels": parcels})


def resident_mib() -> float:
    """The process's resident set now (MiB), or its peak where the system does not tell the current one."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


class MemoryLog:
    """The resident set (MiB) at every tenth of a run, as its progress callback (fraction done, 0..1)."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float]] = []

    def __call__(self, fraction: float) -> None:
        if fraction >= 0.1 * len(self.rows):
            self.rows.append((fraction, resident_mib()))

    def growth_per_hour(self, duration: float) -> float:
        """MiB per simulated hour over the rows after the first tenth (least squares); nan with fewer than two."""
        rows = [(f, m) for f, m in self.rows if f >= 0.1]
        if len(rows) < 2:
            return float("nan")
        f, m = np.array(rows).T
        return float(np.polyfit(f * duration / 3600.0, m, 1)[0])


def main() -> None:
    from virtual_vehicle.run.sim import resume, run, run_network

    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--interval", type=float, default=3.0, help="seconds between arrivals (the junction takes about "
                    "one parcel per 2.9 s: feed it faster and the queue at the entry grows)")
    ap.add_argument("--checkpoint", default=None, help="checkpoint file (default: none)")
    ap.add_argument("--resume", action="store_true", help="continue from --checkpoint instead of starting afresh")
    args = ap.parse_args()
    if args.resume and not args.checkpoint:
        ap.error("--resume needs --checkpoint")
    sc = hour_scenario(args.minutes, args.interval)
    memory = MemoryLog()
    start = time.perf_counter()
    if args.resume:
        res = resume(args.checkpoint, memory)
    elif args.checkpoint:
        res = run_network(sc.build(), memory, checkpoint=args.checkpoint, checkpoint_every=300.0)
    else:
        res = run(sc.build(), memory)
    wall = time.perf_counter() - start
    s = res.summary()
    so, plant = s["sorting"], s["plant"]
    print(f"# {sc.name}: {len(sc.parcels)} parcels due, {sc.duration:g} s simulated in {wall:.0f} s "
          f"({sc.duration / wall:.2f}x real time)")
    for key in ("correct", "misrouted", "lost", "on_array", "waiting", "collisions", "throughput_per_hour",
                "delivery_time_mean_s", "delivery_time_max_s", "entry_delay_mean_s"):
        print(f"{key:>24}: {so[key]}")
    print(f"{'undetected_overlaps':>24}: {plant['undetected_overlaps']}")
    print("resident MiB at each tenth: " + ", ".join(f"{m:.0f}" for _, m in memory.rows)
          + f"; growth after the first tenth {memory.growth_per_hour(sc.duration):.1f} MiB per simulated hour")
    broken = []
    if so["collisions"] or plant["undetected_overlaps"]:
        broken.append("parcels touched")
    if so["misrouted"] or so["lost"]:
        broken.append("a parcel went astray")
    if not all(np.all(np.isfinite(p.trajectory.states)) for p in res.parcels):
        broken.append("a state is not finite")
    if so["waiting"] > max(3, 0.05 * len(sc.parcels)):
        broken.append(f"the queue at the entry grew ({so['waiting']} parcels never got on)")
    short = hour_scenario(1.0)
    a, b = run(short.build()), run(short.build())
    if not all(np.array_equal(x.trajectory.states, y.trajectory.states) for x, y in zip(a.parcels, b.parcels)):
        broken.append("the same seed gave different results")
    print("invariants: " + ("all held" if not broken else "BROKEN: " + "; ".join(broken)))
    sys.exit(1 if broken else 0)


if __name__ == "__main__":
    main()
