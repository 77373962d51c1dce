"""How fast this design could go with no Python at all (issue: performance at facility scale). Prints tables;
asserts nothing about time.

The engine and the plant do their arithmetic in compiled kernels (numba) called from Python. This runs the two
target cases of the issue with every compiled entry point of the package timed (each call from Python, with the
price of passing its arguments in), and prints what share of the wall time they take and the real-time factor
that their work alone allows: the ceiling of any rewrite that keeps these kernels and removes every line of
Python around them. The price of a call is what passing its arguments in and its results out costs: the first
measured by calling a compiled function that does nothing with the same arguments (numba reads every argument's
type on every call: ~2 us for the engine's, whose segment is a tuple of 25 arrays), the second as the arrays
returned (each made into a numpy array, ~0.4 us) times the measured price of returning one.

- ``coulomb1``: one parcel on 30 x 30 cells under the paper's Coulomb law, oscillating in the inward field for 5 s
  (``bench_perf.py`` (b); target 1000x real time);
- ``hall200``: 200 parcels on 100 x 100 cells with the 100 Hz distributed sorter under ideal rounds
  (``bench_scale.py``'s largest; target 50x), for ``--seconds`` (default 2 s: the first second is mostly routing
  set-up, after it most parcels move).

Compiled code called from other compiled code is inside its caller's figure. An entry point kept out of reach of
module attributes (in a container, or bound before this patched the modules) is not timed: the compiled share
shown is a lower bound, and the ceiling an upper one.

Run: ``python benchmarks/bench_ceiling.py`` (or ``make bench``).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

TARGETS = {"coulomb1": 1000.0, "hall200": 50.0}


@dataclass
class EntryPoint:
    """Calls of one compiled entry point from Python: how many, the seconds inside them, and the arguments and
    result of the latest (for pricing a call)."""

    calls: int = 0
    seconds: float = 0.0
    args: tuple = field(default=(), repr=False)
    kwargs: dict = field(default_factory=dict, repr=False)
    result: object = field(default=None, repr=False)


def package_modules() -> list:
    """Every module of the package (imported), where :func:`timed_kernels` looks for compiled functions."""
    import virtual_vehicle

    return [virtual_vehicle] + [importlib.import_module(m.name)
                                for m in pkgutil.walk_packages(virtual_vehicle.__path__, "virtual_vehicle.")]


@contextmanager
def timed_kernels():
    """Within the block, every compiled (numba) function that a module of the package holds as an attribute is
    replaced, in every module holding it, by a wrapper that times its calls. Yields {qualified name: EntryPoint};
    puts the originals back on leaving."""
    from numba.core.registry import CPUDispatcher

    stats: dict[str, EntryPoint] = {}
    wrappers: dict[int, object] = {}
    patched: list[tuple[object, str, object]] = []

    def wrap(dispatcher, label):
        entry = stats.setdefault(label, EntryPoint())
        clock = time.perf_counter

        def timed(*args, **kwargs):
            start = clock()
            result = dispatcher(*args, **kwargs)
            entry.seconds += clock() - start
            entry.calls += 1
            entry.args, entry.kwargs, entry.result = args, kwargs, result
            return result

        timed.__wrapped__ = dispatcher
        return timed

    for mod in package_modules():
        for name, obj in list(vars(mod).items()):
            if isinstance(obj, CPUDispatcher):
                if id(obj) not in wrappers:
                    wrappers[id(obj)] = wrap(obj, f"{obj.py_func.__module__}.{obj.py_func.__qualname__}")
                patched.append((mod, name, obj))
                setattr(mod, name, wrappers[id(obj)])
    try:
        yield stats
    finally:
        for mod, name, obj in patched:
            setattr(mod, name, obj)


@cache
def _nothing():
    """A compiled function of any arguments that returns at once (compiled once per argument types)."""
    from numba import njit

    @njit
    def nothing(*args):
        return 0

    return nothing


def _fastest(fn, args: tuple, repeats: int) -> float:
    """Seconds a call ``fn(*args)`` takes: the fastest of five rounds of ``repeats`` calls (after one to compile)."""
    fn(*args)
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeats):
            fn(*args)
        best = min(best, (time.perf_counter() - start) / repeats)
    return best


@cache
def array_return_price() -> float:
    """Seconds it costs to return one array made in compiled code to Python (numba makes it a numpy array): a
    compiled function that makes a small array and returns it, less one that makes it and returns a float."""
    from numba import njit

    @njit
    def returned(x):
        return np.empty(6)

    @njit
    def kept(x):
        a = np.empty(6)
        return a[0] * 0.0

    return max(_fastest(returned, (1.0,), 20000) - _fastest(kept, (1.0,), 20000), 0.0)


def arrays_in(value) -> int:
    """The numpy arrays in ``value``, through nested tuples."""
    if isinstance(value, np.ndarray):
        return 1
    if isinstance(value, tuple):
        return sum(arrays_in(v) for v in value)
    return 0


def call_price(entry: EntryPoint, repeats: int = 2000) -> float:
    """Seconds a call like ``entry``'s latest costs besides its work: passing its arguments in (a compiled
    function that returns at once, called with them) and its arrays out (:func:`array_return_price` each)."""
    args = entry.args + tuple(entry.kwargs.values())
    return _fastest(_nothing(), args, repeats) + arrays_in(entry.result) * array_return_price()


def run_case(case: str, seconds: float | None = None) -> dict:
    """Run ``case`` once unmeasured (to load numba's cached code; every run builds its models anew, so the timed
    one solves its support patterns as a first run does) and once with its kernels timed, which must end where the
    plain run ended; returns the figures (times in s)."""
    from virtual_vehicle.run.warm import warm_up

    if case == "coulomb1":
        import bench_perf as b

        from virtual_vehicle.engine.dynamics import ParcelModel, integrate

        simulated = 5.0 if seconds is None else seconds

        def go():
            model = ParcelModel(b.CELLS, b.SPEC, b.FIELDS_B["coulomb"], b.LAWS["coulomb"])
            return integrate(model, b.Y0_IN, 0.0, simulated, sample_dt=simulated).states[-1].tolist()
    elif case == "hall200":
        import bench_scale

        from virtual_vehicle.config.scenario import parse_scenario
        from virtual_vehicle.run.sim import run_network

        simulated = 2.0 if seconds is None else seconds
        text = bench_scale.scenario(100, 200, simulated)

        def go():
            res = run_network(parse_scenario(text).build())
            return [p.trajectory.states[-1].tolist() for p in res.parcels]
    else:
        raise ValueError(f"unknown case {case!r}: choose from {sorted(TARGETS)}")
    warm_up()
    plain = go()
    with timed_kernels() as stats:
        start = time.perf_counter()
        end = go()
        wall = time.perf_counter() - start
    if end != plain:
        raise RuntimeError(f"{case}: the timed run ended elsewhere than the plain one")
    called = {name: e for name, e in stats.items() if e.calls}
    inside = sum(e.seconds for e in called.values())
    price = {name: call_price(e) * e.calls for name, e in called.items()}
    work = max(inside - sum(price.values()), 0.0)
    return {"case": case, "simulated": simulated, "wall": wall, "inside": inside, "calls": sum(
        e.calls for e in called.values()), "price": sum(price.values()), "work": work, "target": TARGETS[case],
        "kernels": sorted(((name, e.calls, e.seconds, price[name]) for name, e in called.items()),
                          key=lambda k: -k[2])}


def _x(simulated: float, seconds: float) -> str:
    return f"{simulated / seconds:10.1f}" if seconds > 0 else f"{'inf':>10}"


def report(results: list[dict], top: int = 8) -> None:
    print("# What the compiled kernels alone allow: wall time, the time inside compiled calls from Python, and the")
    print("# real-time factor of that work without the price of the calls (the ceiling of a design that keeps them)")
    print(f"{'case':10s} {'sim s':>6s} {'wall s':>8s} {'x real':>10s} {'compiled s':>10s} {'share':>6s} "
          f"{'calls':>7s} {'call price s':>12s} {'ceiling x':>10s} {'target x':>9s}")
    for r in results:
        print(f"{r['case']:10s} {r['simulated']:6.1f} {r['wall']:8.3f} {_x(r['simulated'], r['wall'])} "
              f"{r['inside']:10.3f} {100 * r['inside'] / r['wall']:5.0f}% {r['calls']:7d} {r['price']:12.4f} "
              f"{_x(r['simulated'], r['work'])} {r['target']:9.0f}")
    for r in results:
        budget = r["simulated"] / r["target"]
        print(f"\n## {r['case']}: the target allows {budget * 1e3:.1f} ms of wall time; the kernels' work takes "
              f"{r['work'] * 1e3:.1f} ms ({r['work'] / budget:.1f}x the budget)")
        print(f"{'entry point':58s} {'calls':>7s} {'inside s':>9s} {'us/call':>8s} {'price us/call':>13s}")
        for name, calls, seconds, price in r["kernels"][:top]:
            print(f"{name:58s} {calls:7d} {seconds:9.4f} {seconds / calls * 1e6:8.1f} {price / calls * 1e6:13.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", choices=sorted(TARGETS), action="append",
                        help="a case to run (repeat for more; default both)")
    parser.add_argument("--seconds", type=float, help="simulated time (default 5 s for coulomb1, 2 s for hall200)")
    args = parser.parse_args()
    report([run_case(case, args.seconds) for case in (args.case or sorted(TARGETS))])


if __name__ == "__main__":
    main()
