"""The sorter's liveness under a randomized stress test (issue 33): generated floors, a table a seed.

Every seed draws a small floor (:func:`virtual_vehicle.analysis.stress.random_floor`: holes, one-way aisles, parking
bays with a sequenced stream, 1-3 entries and exits, every exit reachable) and runs it; the table gives what the
sorting report finds (delivered, misrouted, lost, collisions, stalls by kind) and one line on each stall
(where it stands) under its row. Prints figures; asserts nothing.

Run: ``python benchmarks/stress_sorter.py [--seeds 200] [--first 0] [--duration 16] [--parcels 8]``.
"""

from __future__ import annotations

import argparse
import time

from virtual_vehicle.analysis.stress import stress

COLUMNS = ("seed", "entries", "exits", "holes", "one_way", "parking", "correct", "misrouted", "lost", "collisions",
           "on_array", "waiting", "deadlocks", "waits")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=200)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--duration", type=float, default=16.0)
    parser.add_argument("--parcels", type=int, default=8)
    parser.add_argument("--wait-bound", type=float, default=4.0)
    args = parser.parse_args()
    print(" ".join(f"{c:>9}" for c in COLUMNS), flush=True)
    rows = []
    start = time.perf_counter()
    for seed in range(args.first, args.first + args.seeds):
        row = stress([seed], parcels=args.parcels, duration=args.duration, wait_bound=args.wait_bound)[0]
        rows.append(row)
        print(" ".join(f"{row[c]!s:>9}" for c in COLUMNS), flush=True)
        for line in row["why"]:
            print("   ", line, flush=True)
    total = {k: sum(r[k] for r in rows) for k in ("correct", "misrouted", "lost", "collisions", "deadlocks", "waits")}
    print(f"{len(rows)} seeds in {time.perf_counter() - start:.0f} s: {total}; seeds with a deadlock: "
          f"{sum(r['deadlocks'] > 0 for r in rows)}, with a lone wait: {sum(r['waits'] > 0 for r in rows)}")


if __name__ == "__main__":
    main()
