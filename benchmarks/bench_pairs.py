"""Pairs benchmark (issue: the engine rebuilt, item 5, linear in parcels): wall time per simulated second of N
parcels on a 100 x 100 array (pitch 0.1 m) under a constant uniform field, for N = 25, 50, 100, 200, under the
viscous, the Coulomb and the stick-slip law (the default), and the exponent of wall time against N fitted over those
runs. Prints a table; asserts nothing about time.

Parcels of 0.22 x 0.22 m sit on a 0.5 m lattice (rows of 12 from the south-west corner, 0.28 m apart), so the
parcels that could meet are each one's lattice neighbours: a planner linear in parcels does work linear in N.
The parcels start at rest. The field drives every wheel along x: at 0.2 m/s under the viscous law (the parcels
relax to riding it); at 3 m/s under the Coulomb law, whose parcels accelerate at mu g = 1.96 m/s^2 whatever their
speed, so that they stay slower than their wheels (the paper's sliding assumption, checked) for 1.5 s: use
``--seconds`` up to that; at 0.5 m/s under the stick-slip law (mu 0.5), whose parcels catch up with their wheels
after 0.1 s and then ride them. Each configuration runs in its own process after numba's compiled code is loaded
(:func:`~virtual_vehicle.run.warm.warm_up`), outside the timed run.

Run: ``python benchmarks/bench_pairs.py`` (``--seconds``, ``--counts 25 50``, ``--laws viscous stick_slip``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

MU = {"viscous": 2.0, "coulomb": 0.2, "stick_slip": 0.5}
"""Each law's friction coefficient (viscous in s/m, Coulomb and stick-slip kinetic dimensionless; stick-slip's static
one the parcel's default, equal to it)."""
FIELD = {"viscous": [0.2, 0.0], "coulomb": [3.0, 0.0], "stick_slip": [0.5, 0.0]}
"""Each law's wheel velocity (m/s)."""


def scenario(parcels: int, law: str, seconds: float) -> dict:
    """The scenario of ``parcels`` parcels under ``law`` for ``seconds`` simulated s, as a dict of the TOML's
    tables."""
    spots = [(0.3 + 0.5 * i, 0.3 + 0.5 * j) for j in range(19) for i in range(12)]
    if parcels > len(spots):
        raise SystemExit(f"the lattice holds {len(spots)} parcels, not {parcels}")
    return {
        "name": f"pairs_{law}_{parcels}", "duration": seconds, "output_dt": 0.05,
        "array": {"kind": "grid", "nx": 100, "ny": 100, "pitch": 0.1},
        "field": {"kind": "uniform", "velocity": FIELD[law]},
        "friction": {"law": law},
        "parcels": [{"name": f"p{k}", "length": 0.22, "width": 0.22, "mass": 1.5, "mu": MU[law], "x": x, "y": y}
                    for k, (x, y) in enumerate(spots[:parcels])],
    }


def one(parcels: int, law: str, seconds: float) -> dict:
    """Run one configuration here; return its figures."""
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.sim import run
    from virtual_vehicle.run.warm import warm_up

    setup = parse_scenario(scenario(parcels, law, seconds)).build()
    warm_up()
    start = time.perf_counter()
    res = run(setup)
    wall = time.perf_counter() - start
    plant = res.stats["plant"]
    return {"parcels": parcels, "law": law, "wall_s": wall, "wall_per_sim_s": wall / seconds,
            "real_time_factor": seconds / wall, "windows": plant["windows"], "grouped_steps": plant["grouped_steps"],
            "contacts": plant["parcel_contacts"], "undetected_overlaps": plant["undetected_overlaps"],
            "whole_time": sum(p.trajectory.t_end == seconds for p in res.parcels),
            "sliding_kept": sum(p.sliding_violation is None for p in res.parcels)}


def exponent(counts, walls) -> float:
    """The slope of log(wall) against log(N): 1 is linear in parcels, 2 quadratic."""
    return float(np.polyfit(np.log(counts), np.log(walls), 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--counts", type=int, nargs="+", default=[25, 50, 100, 200])
    ap.add_argument("--laws", nargs="+", default=["viscous", "coulomb"], choices=sorted(MU))
    ap.add_argument("--one", nargs=2, metavar=("PARCELS", "LAW"))
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(int(args.one[0]), args.one[1], args.seconds)))
        return
    print(f"# {args.seconds:g} s simulated on 100 x 100 cells, uniform field (viscous 0.2 m/s, Coulomb 3 m/s, "
          "stick-slip 0.5 m/s), parcels at rest on a 0.5 m lattice")
    print(f"{'law':>11}{'parcels':>9}{'wall s':>10}{'wall/sim s':>12}{'x real':>9}{'windows':>9}{'grouped':>9}"
          f"{'contacts':>10}{'overlaps':>10}")
    for law in args.laws:
        rows = []
        for n in args.counts:
            out = subprocess.run([sys.executable, __file__, "--one", str(n), law, "--seconds", str(args.seconds)],
                                 capture_output=True, text=True, check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(r)
            print(f"{law:>11}{n:>9}{r['wall_s']:>10.3f}{r['wall_per_sim_s']:>12.3f}{r['real_time_factor']:>9.2f}"
                  f"{r['windows']:>9}{r['grouped_steps']:>9}{r['contacts']:>10}{r['undetected_overlaps']:>10}",
                  flush=True)
        if len(rows) > 1:
            print(f"{law:>11}  wall ~ N^{exponent([r['parcels'] for r in rows], [r['wall_s'] for r in rows]):.2f}")


if __name__ == "__main__":
    main()
