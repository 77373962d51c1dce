"""Stick-slip benchmark (issue 32, items 1 and 4): one parcel crossing a 30 x 30 grid (pitch 0.1 m, parcel 0.4 x 0.3
m, 2 kg, uniform field 0.2 m/s, 5 s simulated, as bench_engine's crossing) under the stick-slip law run (i) by the
fixed-step complementarity law (fixed mode, dt = 1 ms), (ii) event-driven (event mode: exact modes), and (iii) the
viscous law event-driven, for scale. Prints wall time, real-time factor, events, how far (i) ends from (ii), and
where the event-driven run's time goes. Asserts nothing about time.

Run: ``python benchmarks/bench_stick_events.py`` (``--no-profile`` for the table alone).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from virtual_vehicle.engine import _kernel, dynamics
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws

from bench_engine import best_of  # (run as a script: its folder is on the path)

CELLS = layout.grid(30, 30, 0.1)
V = fields.Uniform((0.2, 0.0)).velocities(CELLS)
Y0 = [0.52, 1.47, 0.0, 0.0, 0.0, 0.0]
T = 5.0


def spec(law: str):
    """bench_engine's crossing parcel; mu 1 s/m for the viscous law, 0.5 (static 0.6) for stick-slip."""
    if law == "viscous":
        return parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    return parcel.rectangle(0.4, 0.3, 2.0, 0.5, mu_static=0.6)


def run(law: str, mode: str, theta: float = 0.0, dt: float = 1e-3):
    model = ParcelModel(CELLS, spec(law), V, laws.LAWS[law])  # fresh: nothing cached between runs
    return integrate(model, [*Y0[:2], theta, *Y0[3:]], 0.0, T, mode=mode, dt=dt, sample_dt=0.01)


CASES = (("(i) stick-slip, fixed step 1 ms", "stick_slip", "fixed", 2),
         ("(ii) stick-slip, event-driven", "stick_slip", "event", 5),
         ("(iii) viscous, event-driven", "viscous", "event", 5))


def table() -> dict:
    print(f"{'case':<34}{'heading':>8}{'wall (ms)':>11}{'real-time x':>13}{'support':>9}{'modes':>7}"
          f"{'end x (m)':>12}{'|dx| vs (ii)':>14}")
    out = {}
    for theta in (0.0, 0.3):
        results = {}
        for label, law, mode, repeat in CASES:
            run(law, mode, theta)  # compiled and warm
            wall, tr = best_of(lambda: run(law, mode, theta), repeat)
            results[label] = (wall, tr)
        exact = results[CASES[1][0]][1]
        for label, (wall, tr) in results.items():
            diff = np.abs(tr.states[-1, :2] - exact.states[-1, :2]).max() if "stick-slip" in label else np.nan
            support = sum(e.kind == "support" for e in tr.events)
            print(f"{label:<34}{theta:>8.1f}{wall * 1e3:>11.1f}{tr.t_end / wall:>13.0f}{support:>9}"
                  f"{tr.stats.get('mode_changes', 0):>7}{tr.states[-1, 0]:>12.6f}{diff:>14.1e}")
            out[(label, theta)] = wall
    return out


def profile(repeat: int = 5) -> None:
    """Where the event-driven run's time goes: the compiled event loop (one call takes most events) against the
    Python around it (what it hands back: deciding the mode, the wheels of a new support set, the support lookup)."""
    from virtual_vehicle.engine import _modeloop  # (here: alternate.py runs this file's run() on older packages)

    parts = {"compiled event loop (run_modes, all of it)": (_modeloop, "run_modes"),
             "compiled run_mode (integration, events)": (_kernel, "run_mode"),
             "decide_kernel (mode, projection, facets)": (dynamics, "decide_kernel"),
             "breaking_kernel (wheels leaving stick)": (dynamics, "breaking_kernel"),
             "mode tuple": (dynamics, "_mode_tuple"),
             "wheels of a new support set": (laws.StickSlipLaw, "wheel_arrays"),
             "mode changes as events": (dynamics, "_mode_change_events"),
             "support lookup and solve (piece_for)": (ParcelModel, "piece_for"),
             "support events' segment": (dynamics._Segment, "__init__")}
    spent = {name: 0.0 for name in parts}
    calls = {name: 0 for name in parts}
    saved = {}
    for name, (owner, attr) in parts.items():
        fn = getattr(owner, attr)
        saved[name] = fn

        def timed(*a, _fn=fn, _name=name, **k):
            t = time.perf_counter()
            try:
                return _fn(*a, **k)
            finally:
                spent[_name] += time.perf_counter() - t
                calls[_name] += 1

        setattr(owner, attr, timed)
    try:
        t0 = time.perf_counter()
        for _ in range(repeat):
            tr = run("stick_slip", "event")
        wall = (time.perf_counter() - t0) / repeat
    finally:
        for name, (owner, attr) in parts.items():
            setattr(owner, attr, saved[name])
    print(f"\n## Where the event-driven run's time goes (heading 0, mean of {repeat}, timers included): "
          f"{wall * 1e3:.1f} ms, {len(tr.events)} support and {tr.stats['mode_changes']} mode events")
    print(f"{'part':<42}{'calls':>7}{'ms':>9}{'share':>8}{'us/call':>10}")
    for name in parts:
        n = calls[name] / repeat
        ms = spent[name] / repeat * 1e3
        print(f"{name:<42}{n:>7.0f}{ms:>9.2f}{ms / (wall * 1e3):>8.0%}{(ms * 1e3 / n if n else 0):>10.1f}")
    print("(the parts overlap nothing: each is called from the engine's Python between compiled calls; those the "
          "compiled loop calls itself are not counted)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-profile", action="store_true")
    args = parser.parse_args()
    print(f"# stick-slip event benchmark - {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}, numpy {np.__version__}")
    print(f"\n## One parcel crossing 30x30, {T:g} s simulated")
    walls = table()
    fixed, event, viscous = (walls[(label, 0.0)] for label, *_ in CASES)
    print(f"\nheading 0: event-driven stick-slip is {fixed / event:.1f}x faster than the fixed step and "
          f"{event / viscous:.1f}x slower than the viscous law; target (issue 32): >= 1000x real time")
    if not args.no_profile:
        profile()


if __name__ == "__main__":
    main()
