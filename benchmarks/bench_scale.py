"""Scale benchmark (issue: performance at facility scale): real-time factor and peak memory of networked runs with
100 Hz distributed control (the Virtual Vehicle sorter) under ideal rounds, for 1 to 200 parcels on 30 x 30
and 100 x 100 arrays. Prints a table; asserts nothing about time.

Each configuration runs in its own process (so that its peak resident memory is its own): parcels of 0.25 x 0.22 m
on 10 cm cells, placed on a 0.55 m lattice (25 fit on 30 x 30 with the gaps the sorter keeps), labelled for one exit lane on the east edge (every cell reads labels so
they get their vehicle records where they stand), simulated for ``--seconds`` (default 1 s).

Each configuration runs three times: as by default (quiet control ticks stepped for all parcels at once,
``integrator.batch``; the sorter stepped only on the cells that changed, ``control.changed_only``), with every parcel
integrated on its own, and with every cell stepped every tick, so the table shows what each buys side by side.

Run: ``python benchmarks/bench_scale.py`` (or ``make bench``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


# Per law, the parcels' friction: viscous in s/m (the historical table); stick-slip dimensionless, kinetic and static,
# rubber roller on corrugated cardboard as the bundled transport scenarios have it.
FRICTION = {"viscous": {"mu": 2.0}, "stick_slip": {"mu": 0.6, "mu_static": 0.8}}


def scenario(side: int, parcels: int, seconds: float, batch: bool = True, changed_only: bool = True,
             law: str = "viscous") -> dict:
    pitch = 0.1
    spacing = 0.55  # m between parcel centres: the sorter keeps two free cells around every parcel
    coords = [0.2 + spacing * k for k in range(int((side * pitch - 0.4) / spacing) + 1)]
    spots = [(x, y) for y in coords for x in coords if x < (side - 5) * pitch]
    if len(spots) < parcels:
        raise SystemExit(f"a {side} x {side} array holds {len(spots)} parcels this way, not {parcels}")
    lane_y0 = (side // 2 - 2) * pitch - 0.05
    control = {"program": "sort", "period": 0.01, "speed": 0.3, "gap": 2,
               # every cell reads labels, so the parcels placed on the floor get their vehicle records
               "entries": [[[-0.05, -0.05], [(side - 5) * pitch, -0.05], [(side - 5) * pitch, side * pitch],
                            [-0.05, side * pitch]]],
               "exits": [[[(side - 4) * pitch - 0.05, lane_y0], [side * pitch - 0.05, lane_y0],
                          [side * pitch - 0.05, lane_y0 + 0.4], [(side - 4) * pitch - 0.05, lane_y0 + 0.4]]]}
    if not changed_only:  # named only when off, so that alternate.py runs this on commits from before the option
        control["changed_only"] = False
    return {
        "name": f"scale_{side}x{side}_{parcels}", "duration": seconds, "output_dt": 0.05,
        "array": {"kind": "grid", "nx": side, "ny": side, "pitch": pitch},
        "control": control,
        "friction": {"law": law},
        "integrator": {"batch": batch},
        "parcels": [{"name": f"p{k}", "length": 0.22, "width": 0.22, "mass": 1.5, **FRICTION[law], "x": x,
                     "y": y, "destination": 0} for k, (x, y) in enumerate(spots[:parcels])],
    }


def one(side: int, parcels: int, seconds: float, batch: bool = True, changed_only: bool = True,
        law: str = "viscous") -> dict:
    """Run one configuration here; return its figures."""
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.sim import NetworkRun
    from virtual_vehicle.run.warm import warm_up

    setup = parse_scenario(scenario(side, parcels, seconds, batch, changed_only, law)).build()
    load = warm_up()  # numba's cached code, loaded outside the timed run as the imports are
    job = NetworkRun(setup)
    start = time.perf_counter()
    res = job.run(None)
    wall = time.perf_counter() - start
    stepped = job.stepper.stepped / job.stepper.ticks if job.stepper is not None else setup.cells.n
    moved = sum(float(abs(p.trajectory.states[-1, 0] - p.trajectory.states[0, 0])) > 0.01 for p in res.parcels)
    return {"cells": side * side, "parcels": parcels, "simulated_s": seconds, "wall_s": wall,
            "real_time_factor": seconds / wall, "peak_rss_MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "windows": res.stats["plant"]["windows"], "quiet_steps": res.stats["plant"]["quiet_steps"],
            "parcels_moving": moved, "engine_load_s": load, "cells_stepped_%": 100 * stepped / setup.cells.n}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--one", nargs=2, type=int, metavar=("SIDE", "PARCELS"))
    ap.add_argument("--unbatched", action="store_true", help="with --one: integrate every parcel on its own")
    ap.add_argument("--every-cell", action="store_true", help="with --one: step every cell every tick")
    ap.add_argument("--law", choices=sorted(FRICTION), default="viscous",
                    help="the parcels' friction law (default viscous, the table's history)")
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(*args.one, args.seconds, batch=not args.unbatched, changed_only=not args.every_cell,
                             law=args.law)))
        return
    print(f"# Networked runs, 100 Hz distributed control (sorter), ideal rounds, {args.seconds:g} s simulated, "
          f"{args.law} friction")
    print("# default: quiet ticks of all parcels in one compiled call, the sorter stepped on the cells that changed;")
    print("# alone: each parcel integrated on its own; every cell: the sorter stepped on every cell every tick")
    print(f"{'array':>9}{'parcels':>9}{'moving':>8}{'quiet %':>9}{'cells %':>9}{'wall s':>9}{'x real time':>13}"
          f"{'alone x':>9}{'every cell x':>14}{'peak MiB':>10}{'alone MiB':>11}")
    loads: list[float] = []
    for side, parcels in ((30, 1), (30, 25), (100, 1), (100, 50), (100, 200)):
        r, alone, every = (_measure(side, parcels, args.seconds, [*flag, "--law", args.law])
                           for flag in ([], ["--unbatched"], ["--every-cell"]))
        quiet = 100 * r["quiet_steps"] / max(1, round(parcels * args.seconds / 0.01))
        print(f"{side}x{side:<6}{parcels:>9}{r['parcels_moving']:>8}{quiet:>9.0f}{r['cells_stepped_%']:>9.1f}"
              f"{r['wall_s']:>9.2f}{r['real_time_factor']:>13.3f}{alone['real_time_factor']:>9.3f}"
              f"{every['real_time_factor']:>14.3f}{r['peak_rss_MiB']:>10.0f}{alone['peak_rss_MiB']:>11.0f}",
              flush=True)
        loads.extend((r["engine_load_s"], alone["engine_load_s"], every["engine_load_s"]))
    print(f"(each process first loads the event engine's compiled code, {min(loads):.2f}-{max(loads):.2f} s, "
          "outside the timed run as its imports are; peak memory includes numba's, about 100 MiB)")


def _measure(side: int, parcels: int, seconds: float, flags: list[str]) -> dict:
    out = subprocess.run([sys.executable, __file__, "--one", str(side), str(parcels), "--seconds", str(seconds),
                          *flags], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
