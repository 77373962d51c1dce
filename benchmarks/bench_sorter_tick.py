"""The sorter's tick alone on the hall (issue 32 item 6): 100 x 100 cells, 200 parcels, 100 Hz, the scenario of
``bench_scale.py --one 100 200``. The run goes on as usual (the plant too); the clock runs only inside the cells'
part of each tick, split into its pieces: reading the sensors (with the tick's faults and arrivals), the labels, choosing the cells to step (the active
set), the compiled policy on them, and the delivery of what they said. Prints ns per cell per tick (over all 10^4
cells, what a tick costs the hall), ticks per second of the cells' part, and the active fraction (cells stepped
over cells; and the cells whose clocks alone ticked). Asserts nothing about time. The machine's load moves these figures: take the best of a few runs.

``--settle K`` leaves the first K ticks (start-up: the gradients spread, most cells step) out of the figures;
``--clock process`` counts the process's CPU time instead of the wall's (steadier on a loaded machine).

Run: ``python benchmarks/bench_sorter_tick.py [--seconds 1] [--law viscous|stick_slip] [--settle 20]
[--clock wall|process]``.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path
import sys

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_scale import scenario  # noqa: E402


def measure(side: int, parcels: int, seconds: float, law: str, settle: int = 0, clock=time.perf_counter) -> dict:
    """Run the hall; the seconds spent in each piece of the cells' part of its ticks, and the cells stepped."""
    import virtual_vehicle.run.network as network
    import virtual_vehicle.run.sim as sim
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.warm import warm_up

    setup = parse_scenario(scenario(side, parcels, seconds, law=law)).build()
    warm_up()
    job = sim.NetworkRun(setup)
    spent: dict[str, float] = defaultdict(float)

    def timed(name, f):
        def run(*a, **k):
            start = clock()
            try:
                return f(*a, **k)
            finally:
                spent[name] += clock() - start
        return run

    begin = timed("sensors", job.begin)
    counted = {"ticks": 0, "stepped": 0, "ticked": 0}

    def settled(*a, **k):  # the figures from tick ``settle`` on
        if job.k == settle:
            spent.clear()
            if job.stepper is not None:
                counted.update(ticks=job.stepper.ticks, stepped=job.stepper.stepped, ticked=job.stepper.ticked)
        return begin(*a, **k)

    job.begin = settled  # faults, arrivals and the sensors read
    labels = network._labels  # where the tick looks it up
    network._labels = timed("labels", labels)
    decide = job._decide
    job._decide = timed("decide", decide)
    program = setup.control.program
    program.step_rows = timed("policy", program.step_rows)
    job.delivery.exchange_changed = timed("delivery", job.delivery.exchange_changed)
    if job.stepper is not None:
        job.stepper.step = timed("stepper", job.stepper.step)
    try:
        job.run(None)
    finally:
        network._labels = labels
    ticks = job.k - settle
    seconds = ticks * setup.control.period
    n = setup.cells.n
    stepped = ((job.stepper.stepped - counted["stepped"]) / max(1, job.stepper.ticks - counted["ticks"])
               if job.stepper is not None else n)
    cells_part = spent["decide"] + spent["sensors"]
    parts = {"sensors": spent["sensors"], "labels": spent["labels"], "active set": spent["stepper"] - spent["policy"],
             "policy": spent["policy"], "delivery": spent["delivery"],
             "rest of the decision": spent["decide"] - spent["labels"] - spent["stepper"] - spent["delivery"]}
    clocks = ((getattr(job.stepper, "ticked", 0) - counted["ticked"]) / max(1, job.stepper.ticks - counted["ticks"])
              if job.stepper is not None else 0)
    return {"cells": n, "parcels": parcels, "ticks": ticks, "law": law, "active_fraction": stepped / n,
            "clocks_only_fraction": clocks / n,
            "ns_per_cell_tick": 1e9 * cells_part / (ticks * n),
            "ns_per_active_cell_tick": 1e9 * spent["policy"] / max(1.0, ticks * stepped),
            "ticks_per_s": ticks / cells_part, "ms_per_simulated_s": 1e3 * cells_part / seconds,
            "parts_ms_per_simulated_s": {k: round(1e3 * v / seconds, 2) for k, v in parts.items()}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--parcels", type=int, default=200)
    ap.add_argument("--law", choices=("viscous", "stick_slip"), default="viscous")
    ap.add_argument("--settle", type=int, default=0)
    ap.add_argument("--clock", choices=("wall", "process"), default="wall")
    args = ap.parse_args()
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    print(json.dumps(measure(100, args.parcels, args.seconds, args.law, args.settle, clock), indent=1))


if __name__ == "__main__":
    main()
