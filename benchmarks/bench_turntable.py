"""Turntable benchmark (issue: the engine rebuilt, item 5): wall time per simulated second of stick-slip parcels
(the default law) on a 30 x 30 array (pitch 0.1 m) turning rigidly at 0.5 rad/s about its middle (a ``rotation``
field), and how many windows the plant's planner cut the run into. Prints a table; asserts nothing about time.

The parcels (0.3 x 0.2 m, 2 kg, mu 0.6 kinetic, 0.8 static) start at rest on a ring 0.9 m from the centre,
evenly spaced, catch up with their wheels in ~0.1 s and then ride the turntable: they never meet. Relative to the
wheels' common velocity the turntable's wheel speeds spread over the whole array (up to 1 m/s), so a planner that
measures in a translating frame cuts the ride into windows of about a tenth of a second; in the field's rotating
frame (``physics.laws.rotating_reach``) a riding parcel stands still. Each configuration runs in its own process
after numba's compiled code is loaded (:func:`~virtual_vehicle.run.warm.warm_up`), outside the timed run.

Run: ``python benchmarks/bench_turntable.py`` (``--counts 2 8``, ``--seconds``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import numpy as np


def scenario(parcels: int, seconds: float) -> dict:
    """The scenario of ``parcels`` parcels for ``seconds`` simulated s, as a dict of the TOML's tables."""
    if not 1 <= parcels <= 12:
        raise SystemExit("the ring holds 1 to 12 parcels")
    angles = 2 * np.pi * np.arange(parcels) / parcels
    return {
        "name": f"turntable_{parcels}", "duration": seconds, "output_dt": 0.05,
        "array": {"kind": "grid", "nx": 30, "ny": 30, "pitch": 0.1},
        "field": {"kind": "rotation", "omega": 0.5, "center": [1.5, 1.5]},
        "friction": {"law": "stick_slip"},
        "parcels": [{"name": f"p{k}", "length": 0.3, "width": 0.2, "mass": 2.0, "mu": 0.6, "mu_static": 0.8,
                     "x": 1.5 + 0.9 * float(np.cos(a)), "y": 1.5 + 0.9 * float(np.sin(a)), "theta": float(a)}
                    for k, a in enumerate(angles)],
    }


_ONE = """
import json, sys, time
sys.path.insert(0, {here!r})
import bench_turntable
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.warm import warm_up
setup = parse_scenario(bench_turntable.scenario({parcels}, {seconds})).build()
warm_up()
start = time.perf_counter()
res = run(setup)
wall = time.perf_counter() - start
print(json.dumps({{"wall": wall, "windows": res.stats["plant"]["windows"],
                  "end": res.parcels[-1].trajectory.states[-1].tolist()}}))
"""


def one(parcels: int, seconds: float) -> dict:
    """One run in a fresh process: its wall time (s), the plant's windows and the last parcel's end state."""
    from pathlib import Path

    code = _ONE.format(here=str(Path(__file__).resolve().parent), parcels=parcels, seconds=seconds)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[2, 8])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    print(f"{'parcels':>8} {'wall (s)':>9} {'s per sim s':>12} {'x real time':>12} {'windows':>8}")
    for n in args.counts:
        r = one(n, args.seconds)
        per = r["wall"] / args.seconds
        print(f"{n:>8} {r['wall']:>9.3f} {per:>12.4f} {1 / per:>12.1f} {r['windows']:>8}")


if __name__ == "__main__":
    main()
