"""Compare the speed of two commits on this noisy machine (issue: performance at facility scale). Prints figures;
asserts nothing about time.

This VM runs the same code up to ~1.5x apart from one process launch to the next, so two tables taken minutes
apart cannot tell a 10 % change from the machine's mood. This runs one case in fresh processes, alternating the two
commits round by round and which goes first (a machine that drifts over the rounds would otherwise favour one), each
commit's source checked out once into a temporary git worktree and run once unmeasured so that numba's compiled
code is cached, and prints every wall time, the medians and in how many rounds the second commit was faster (the
same code against itself reads a few per cent either way, in 3 of 3 rounds one time in four: use many rounds).

Cases (the figures of ``RESULTS.md``):
- ``scale200``: ``run_network`` on 100 x 100 cells with 200 parcels, 1 s simulated (``bench_scale.py``'s largest);
- ``steady200``: the same for 4 s, in which the exit gradient has crossed the hall and all 200 parcels move (the
  first second is mostly routing set-up);
- ``scale1``: the same hall with one parcel (mostly empty floor);
- ``hall200stick``: ``scale200`` on the stick-slip law (the default: most windows ride their wheels);
- ``coulomb1``: one Coulomb parcel oscillating in the inward field for 5 s (``bench_perf.py`` (b)), the fastest of
  five runs in each process (wall and process time: the latter also printed, being less swayed by other jobs);
- ``pairs200``, ``pairs200coulomb``, ``pairs200stick``: 200 parcels on 100 x 100 cells under a constant uniform
  field for 1 s, viscous, Coulomb and stick-slip law (``bench_pairs.py``'s largest: the plant's planner over many
  parcels);
- ``stick1``: one stick-slip parcel crossing 30 x 30 for 5 s event-driven (``bench_stick_events.py`` (ii)), the
  fastest of five runs in each process;
- ``turntable8``: eight stick-slip parcels riding a 30 x 30 turntable for 5 s (``bench_turntable.py``'s larger).

Run: ``python benchmarks/alternate.py a16f5ef HEAD --case scale200 --rounds 6``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_SCALE = """
import json, sys, time
sys.path.insert(0, {bench!r})
import bench_scale
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run_network
setup = parse_scenario(bench_scale.scenario(100, {parcels}, {seconds}, law={law!r})).build()
try:  # load the compiled engine outside the timed run, as the imports are (from 580daa9)
    from virtual_vehicle.run.warm import warm_up
    warm_up()
except ImportError:
    pass
start = time.perf_counter()
res = run_network(setup)
wall = time.perf_counter() - start
print(json.dumps({{{{"wall": wall, "end": res.parcels[-1].trajectory.states[-1].tolist()}}}}))
"""

_PAIRS = """
import json, sys, time
sys.path.insert(0, {bench!r})
import bench_pairs
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.warm import warm_up
setup = parse_scenario(bench_pairs.scenario(200, {law!r}, 1.0)).build()
warm_up()
start = time.perf_counter()
res = run(setup)
wall = time.perf_counter() - start
print(json.dumps({{{{"wall": wall, "end": res.parcels[-1].trajectory.states[-1].tolist()}}}}))
"""

CASES = {
    "scale200": _SCALE.format(parcels=200, seconds=1.0, bench="{bench}", law="viscous"),
    "steady200": _SCALE.format(parcels=200, seconds=4.0, bench="{bench}", law="viscous"),
    "scale1": _SCALE.format(parcels=1, seconds=1.0, bench="{bench}", law="viscous"),
    "hall200stick": _SCALE.format(parcels=200, seconds=1.0, bench="{bench}", law="stick_slip"),
    "pairs200": _PAIRS.format(law="viscous", bench="{bench}"),
    "pairs200coulomb": _PAIRS.format(law="coulomb", bench="{bench}"),
    "pairs200stick": _PAIRS.format(law="stick_slip", bench="{bench}"),
    "turntable8": """
import json, sys, time
sys.path.insert(0, {bench!r})
import bench_turntable
from virtual_vehicle.config.scenario import parse_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.warm import warm_up
setup = parse_scenario(bench_turntable.scenario(8, 5.0)).build()
warm_up()
start = time.perf_counter()
res = run(setup)
wall = time.perf_counter() - start
print(json.dumps({{"wall": wall, "end": res.parcels[-1].trajectory.states[-1].tolist()}}))
""",
    "coulomb1": """
import json, sys, time
sys.path.insert(0, {bench!r})
import bench_perf as b
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
walls, cpus = [], []
for _ in range(5):
    start, cpu = time.perf_counter(), time.process_time()
    tr = integrate(ParcelModel(b.CELLS, b.SPEC, b.FIELDS_B["coulomb"], b.LAWS["coulomb"]), b.Y0_IN, 0.0, 5.0,
                   sample_dt=5.0)
    walls.append(time.perf_counter() - start)
    cpus.append(time.process_time() - cpu)
print(json.dumps({{"wall": min(walls), "cpu": min(cpus), "end": tr.states[-1].tolist()}}))
""",
    "stick1": """
import json, sys, time
sys.path.insert(0, {bench!r})
import bench_stick_events as b
walls = []
for _ in range(6):  # the first compiles and warms
    start = time.perf_counter()
    tr = b.run("stick_slip", "event")
    walls.append(time.perf_counter() - start)
print(json.dumps({{"wall": min(walls[1:]), "end": tr.states[-1].tolist()}}))
""",
}


def _run(src: Path, case: str) -> dict:
    """One fresh process running ``case`` against the package in ``src`` (and this checkout's benchmarks)."""
    code = CASES[case].format(bench=str(ROOT / "benchmarks"))
    env = {**os.environ, "PYTHONPATH": str(src)}  # ahead of the installed (editable) package
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if out.returncode:  # (e.g. this checkout's benchmark names something the older package lacks)
        raise SystemExit(f"case {case!r} failed against {src}:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", help="first commit (any git revision)")
    parser.add_argument("b", help="second commit")
    parser.add_argument("--case", choices=sorted(CASES), default="scale200")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    if args.a == args.b or args.rounds < 1:
        parser.error("name two different revisions and at least one round")
    with tempfile.TemporaryDirectory() as tmp:
        trees: dict[str, Path] = {}
        try:
            for rev in (args.a, args.b):
                path = Path(tmp) / f"tree{len(trees)}"
                subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(path), rev],
                               check=True)
                trees[rev] = path
            walls: dict[str, list[float]] = {rev: [] for rev in trees}
            cpus: dict[str, list[float]] = {rev: [] for rev in trees}  # process time, where the case gives it
            ends: dict[str, list] = {}
            for path in trees.values():  # unmeasured: compiles and caches what numba compiles (from f2d8583)
                _run(path / "src", args.case)
            print(f"# {args.case}: {args.rounds} rounds, {args.a} and {args.b} alternated, wall s")
            print(f"{'round':>5}{args.a:>14}{args.b:>14}")
            for k in range(args.rounds):
                row = {}
                # a, b in even rounds and b, a in odd ones: a machine that speeds up or slows down over the
                # rounds would otherwise favour whichever commit always runs first
                for rev, path in list(trees.items())[::1 if k % 2 == 0 else -1]:
                    r = _run(path / "src", args.case)
                    walls[rev].append(r["wall"])
                    if "cpu" in r:
                        cpus[rev].append(r["cpu"])
                    ends[rev] = r["end"]
                    row[rev] = r["wall"]
                print(f"{k + 1:>5}{row[args.a]:>14.3f}{row[args.b]:>14.3f}")
            med = [statistics.median(walls[rev]) for rev in trees]
            gain = (med[0] - med[1]) / med[0] * 100
            print(f"{'median':>5}{med[0]:>14.3f}{med[1]:>14.3f}   ({args.b} {abs(gain):.1f} % "
                  f"{'faster' if gain >= 0 else 'slower'})")
            # how many rounds agree with the medians: on this VM a few per cent between medians can be its phases
            wins = sum(b < a for a, b in zip(walls[args.a], walls[args.b]))
            print(f"{args.b} faster in {wins} of {args.rounds} rounds")
            if all(len(c) == args.rounds for c in cpus.values()):  # process time: less swayed by other jobs
                cpu = [statistics.median(cpus[rev]) for rev in trees]
                cpu_wins = sum(b < a for a, b in zip(cpus[args.a], cpus[args.b]))
                print(f"process time, median: {cpu[0]:.4f} vs {cpu[1]:.4f} s ({args.b} faster in {cpu_wins} of "
                      f"{args.rounds} rounds); load average at the end {os.getloadavg()[0]:.1f}")
            same = ends[args.a] == ends[args.b]
            print("final states " + ("identical" if same else "differ: " + json.dumps(ends)))
        finally:
            for path in trees.values():
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)], check=False)


if __name__ == "__main__":
    main()
