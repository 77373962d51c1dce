"""Unsynchronised cell clocks on the sorter (issue 33 item 3). Prints figures; asserts nothing.

``sorting_junction`` run with every cell on one shared clock and with every cell on its own (``[control.clock]``
drift +-1 %, jitter 1 ms, several clock seeds): parcels delivered correctly, misrouted and collided, and the ratio
of the unsynchronised mean to the synchronous count (the issue's target: within 5 %), with the wall and process
time of each run (an unsynchronised run steps at every instant some cells tick, up to ``slots`` a period; the
process time is its cost, the wall time also counts whatever else the machine runs). Each run's line also gives
the parcels left at the end (on the array, or not yet put on) and the mean transit time of those delivered, entry
to exit: a finer measure than a count of some dozen parcels, one of which is some 8 %.
``--saturate`` feeds the entry as fast as it accepts (``arrivals = "saturate"``, the scenario's mix repeated so it
never runs dry) and compares delivered parcels per hour (steady state) instead.

Each unsynchronised run also prints how long a sentence waits in its mailbox place (``wait``, in periods, mean over
the sentences read): from the step that put it there (its sender's tick on ideal rounds; the step its last byte
arrived in on the wire) to the tick its cell read it; ``over`` is the share of sentences replaced unread by a newer one.
On one shared clock a sentence is read at the tick after it was sent (1 period, by the model's definition).

Run: ``python benchmarks/bench_clocks.py [--duration 20] [--seeds 5] [--first-seed 0] [--delivery ideal]
[--baud 460800] [--saturate]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from virtual_vehicle.cells.network.clocks import Mailboxes
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run.clocked import ClockedRun
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


class ReadWaits:
    """While in its ``with`` block, every clocked run's mailboxes are watched: the wait of each sentence read, from
    the step that put it in its place to the tick its cell read it (s), summed, and the sentences replaced unread."""

    def __init__(self) -> None:
        self.total, self.read, self.put, self.replaced = 0.0, 0, 0, 0
        self.shortest, self.longest = float("inf"), 0.0
        self.now, self.put_at = 0.0, None
        self._patches = []

    def __enter__(self):
        decide, put, read = ClockedRun._decide, Mailboxes.put, Mailboxes.read
        waits = self

        def _decide(run_, sensors):
            waits.now = run_.span()[0]  # the instant the cells tick: read, then send (see ClockedRun._decide)
            return decide(run_, sensors)

        def _put(mail, arrived):
            hit = arrived.present
            if waits.put_at is None:
                waits.put_at = np.zeros(hit.shape)
            waits.put += int(hit.sum())
            waits.replaced += int((hit & mail.mail.present).sum())
            waits.put_at[hit] = waits.now
            return put(mail, arrived)

        def _read(mail, rows):
            if waits.put_at is not None:
                here = mail.mail.present[rows]
                wait = waits.now - waits.put_at[rows][here]
                waits.total += float(wait.sum())
                waits.read += int(wait.size)
                if wait.size:
                    waits.shortest = min(waits.shortest, float(wait.min()))
                    waits.longest = max(waits.longest, float(wait.max()))
            return read(mail, rows)

        for name, fn in (("_decide", _decide), ("put", _put), ("read", _read)):
            cls = ClockedRun if name == "_decide" else Mailboxes
            self._patches.append((cls, name, getattr(cls, name)))
            setattr(cls, name, fn)
        return self

    def __exit__(self, *exc) -> None:
        for cls, name, fn in self._patches:
            setattr(cls, name, fn)

    def mean(self) -> float | None:
        """Mean wait of a sentence read (s); None when none was."""
        return self.total / self.read if self.read else None


def delivered(sc, clock: dict) -> tuple[dict, float, float, ReadWaits]:
    """The sorting report of ``sc`` under ``clock`` ([control.clock] fields), the run's wall and process time (s)
    and its mailboxes' waits (none counted on one shared clock)."""
    control = sc.control.model_copy(update={"clock": type(sc.control.clock)(**clock)})
    start, cpu = time.perf_counter(), time.process_time()
    with ReadWaits() as waits:
        report = sorting_report(run(sc.model_copy(update={"control": control}).build()))
    return report, time.perf_counter() - start, time.process_time() - cpu, waits


def saturated(sc):
    """``sc`` with its entries fed as fast as they accept, its parcel mix repeated so that none runs dry (one a
    second an entry, above any entry's bound)."""
    per_entry = len(sc.parcels) / len({(p.x, p.y) for p in sc.parcels})
    rounds = int(np.ceil(sc.duration / per_entry))
    parcels = [p.model_copy(update={"name": f"{p.name}_{k}"}) for k in range(rounds) for p in sc.parcels]
    return sc.model_copy(update={"arrivals": "saturate", "parcels": parcels})


def score(report: dict, saturate: bool) -> float:
    """What the runs are compared by: parcels delivered correctly, or delivered per hour when saturated."""
    return report["saturation"]["total"]["delivered_per_hour"] if saturate else report["correct"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="sorting_junction")
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--first-seed", type=int, default=0, help="clock seeds first-seed .. first-seed + seeds - 1")
    parser.add_argument("--drift", type=float, default=0.01)
    parser.add_argument("--jitter", type=float, default=0.001)
    parser.add_argument("--delivery", choices=("ideal", "wire"), default="ideal")
    parser.add_argument("--baud", type=float, default=460800.0, help="the wire's line rate, bits/s")
    parser.add_argument("--saturate", action="store_true", help="feed the entries as fast as they accept")
    args = parser.parse_args()
    sc, _ = load_scenario(args.scenario)
    control = sc.control.model_copy(update={"delivery": args.delivery,
                                            "wire": sc.control.wire.model_copy(update={"baud": args.baud})})
    sc = sc.model_copy(update={"duration": args.duration, "control": control})
    if args.saturate:
        sc = saturated(sc)
    print(f"{args.scenario}, {args.duration:g} s, {args.delivery} delivery"
          + (f" at {args.baud:g} baud" if args.delivery == "wire" else ""))
    print(f"{'clocks':<34} {'correct':>7} {'per hour':>8} {'misrouted':>9} {'collisions':>10} {'left':>4} "
          f"{'transit s':>9} {'wait':>5} {'over':>6} {'wall s':>7} {'cpu s':>7}")
    period = sc.control.period

    def line(label: str, rep: dict, wall: float, cpu: float, waits: ReadWaits) -> None:
        per_hour = rep["saturation"]["total"]["delivered_per_hour"] if args.saturate else None
        transit = rep["delivery_time_mean_s"]
        wait = "1.00" if waits.mean() is None else f"{waits.mean() / period:.2f}"  # (shared clock: by definition)
        over = "-" if not waits.put else f"{waits.replaced / waits.put:.2%}"
        print(f"{label:<34} {rep['correct']:>7} {'-' if per_hour is None else f'{per_hour:.0f}':>8} "
              f"{rep['misrouted']:>9} {rep['collisions']:>10} {rep['on_array'] + rep['waiting']:>4} "
              f"{'-' if transit is None else f'{transit:.2f}':>9} {wait:>5} {over:>6} {wall:>7.1f} {cpu:>7.1f}",
              flush=True)

    sync, wall, cpu, waits = delivered(sc, {})
    line("one shared clock", sync, wall, cpu, waits)
    counts, transits, mean_waits = [], [], []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        rep, wall, cpu, waits = delivered(sc, {"drift": args.drift, "jitter": args.jitter, "seed": seed})
        counts.append(score(rep, args.saturate))
        transits.append(rep["delivery_time_mean_s"])
        mean_waits.append(waits.mean())
        line(f"own clocks +-{args.drift:.0%}, {args.jitter * 1e3:g} ms, seed {seed}", rep, wall, cpu, waits)
    what = "delivered per hour" if args.saturate else "delivered"
    if None in counts or score(sync, args.saturate) is None:  # saturated runs too short for two deliveries an entry
        print(f"no steady-state rate in {args.duration:g} s: run longer")
        return
    mean, base = float(np.mean(counts)), score(sync, args.saturate)
    ratio = mean / base if base else float("nan")
    print(f"mean over {args.seeds} clock seeds: {mean:.2f} {what} (spread {min(counts):g}..{max(counts):g}), "
          f"{ratio:.1%} of the synchronous run's: {'within' if abs(ratio - 1) <= 0.05 else 'outside'} 5 %")
    if None not in mean_waits:
        print(f"a sentence waits {np.mean(mean_waits) / period:.2f} periods in its mailbox on own clocks (mean over "
              f"seeds), 1 on one shared clock")
    if None not in transits and sync["delivery_time_mean_s"]:
        print(f"mean transit (entry to exit) {np.mean(transits):.2f} s, "
              f"{np.mean(transits) / sync['delivery_time_mean_s']:.1%} of the synchronous run's")


if __name__ == "__main__":
    main()
