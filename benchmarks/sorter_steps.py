"""What the sorter's whole steps on the hall change (issue 32 item 6): the hall of ``bench_sorter_tick.py`` (100 x 100
cells, 200 parcels, 100 Hz, viscous), every cell the changed-cells stepper steps whole classified by what its step
changed - a sentence or wheel speed (``output``), state beyond what it heard and its counters (``state``), only the
words it heard (``heard``), only its counters (the tick each port last heard, the repeats left, the hold's age, the
back-off: ``counters``), or nothing - by whether a parcel covers it (``lit``) and by why it was stepped (the first
that applies of: due by the time, its sensors or label changed, a word it hears changed, its state changed last
tick, its clocks ran last tick; ``full``: a tick that stepped every cell). Ticks before ``--settle`` (the start-up,
while the gradients spread) are counted apart. Prints one line a class, steps a tick and share; asserts nothing.

Run: ``python benchmarks/sorter_steps.py [--seconds 3] [--settle 20]``.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path
import sys

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_scale import scenario  # noqa: E402

COUNTERS = ("heard_at", "again", "hage", "back")


def _leaves(st: dict) -> dict:
    return {f"{k}.{w}" if isinstance(v, dict) else k: a for k, v in st.items()
            for w, a in (v.items() if isinstance(v, dict) else [(None, v)])}


def measure(seconds: float, settle: int) -> tuple[Counter, int]:
    import virtual_vehicle.run.sim as sim
    from virtual_vehicle.cells.network import programs
    from virtual_vehicle.cells.network.messages import rows_differ
    from virtual_vehicle.cells.sorting import sorter
    from virtual_vehicle.config.scenario import parse_scenario

    job = sim.NetworkRun(parse_scenario(scenario(100, 200, seconds, law="viscous")).build())
    tally: Counter = Counter()
    why = {"reason": None}
    step, run = programs.ChangedCells.step, sorter.Sorter._run

    def stepper_step(self, state, inputs, inbox_changed=None):  # why each cell would be stepped (as step chooses)
        last, n = self.last, len(inputs.sensors)
        why["reason"], why["k"] = None, self.ticks
        if last is not None and not self.skip and inbox_changed is not None:
            sensed = rows_differ([np.asarray(inputs.sensors)], [last["sensors"]], n)
            if inputs.labels is not None and last["labels"] is not None:
                sensed |= inputs.labels != last["labels"]
            ticking = last.get("ticking")
            reason = np.full(n, "", dtype=object)
            reason[last["unsettled"]] = "state changed last tick"
            if ticking is not None:
                reason[ticking] = "clocks ran last tick"
            reason[inbox_changed] = "new words"
            reason[sensed] = "sensors/label"
            reason[self.program.due(inputs.t, state, inputs.config)] = "due"
            why["reason"] = reason
        return step(self, state, inputs, inbox_changed)

    def sorter_run(self, state, inputs, rows, new, out, wheels):  # what each whole step changed
        before = {k: a[rows].copy() for k, a in _leaves(state).items()}
        said = [a[rows].copy() for a in (*out.arrays, wheels)]
        masks = run(self, state, inputs, rows, new, out, wheels)
        after = _leaves(new)
        m = len(rows)
        changed = {k: (after[k][rows] != b).reshape(m, -1).any(axis=1) for k, b in before.items()}
        output = np.zeros(m, bool)
        for a, b in zip((*out.arrays, wheels), said):
            output |= (a[rows] != b).reshape(m, -1).any(axis=1)
        state_words = np.zeros(m, bool)
        heard = np.zeros(m, bool)
        counters = np.zeros(m, bool)
        for k, c in changed.items():
            if k.startswith("heard."):
                heard |= c
            elif k in COUNTERS:
                counters |= c
            else:
                state_words |= c
        lit = np.asarray(inputs.sensors)[rows].any(axis=1)
        phase = "start-up" if why.get("k") is None or why["k"] < settle else "settled"
        for j in range(m):
            what = ("output" if output[j] else "state" if state_words[j] else "heard" if heard[j]
                    else "counters" if counters[j] else "nothing")
            reason = "full" if why["reason"] is None else why["reason"][rows[j]]
            tally[(phase, what, "lit" if lit[j] else "dark", reason)] += 1
        return masks

    programs.ChangedCells.step, sorter.Sorter._run = stepper_step, sorter_run
    try:
        job.run(None)
    finally:
        programs.ChangedCells.step, sorter.Sorter._run = step, run
    return tally, job.stepper.ticks


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--settle", type=int, default=20, help="ticks counted as the start-up")
    args = ap.parse_args()
    tally, ticks = measure(args.seconds, args.settle)
    for phase, n_ticks in (("start-up", args.settle), ("settled", ticks - args.settle)):
        rows = {k[1:]: v for k, v in tally.items() if k[0] == phase}
        total = sum(rows.values())
        print(f"{phase}: {n_ticks} ticks, {total / max(1, n_ticks):.0f} whole steps a tick")
        for (what, lit, reason), v in sorted(rows.items(), key=lambda kv: -kv[1]):
            if v >= 0.002 * total:
                print(f"  {what:9s} {lit:5s} {reason:24s} {v / max(1, n_ticks):8.1f} a tick {100 * v / total:5.1f} %")


if __name__ == "__main__":
    main()
