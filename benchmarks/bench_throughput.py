"""Saturation throughput benchmark (issue 33, item 6). Prints figures; asserts nothing.

Every entry of a sorting scenario is fed as fast as it accepts (``arrivals = "saturate"``) and the run's
per-parcel table gives parcels per hour per entry (steady state: between the first and the last delivery), set
against the kinematic bound ``speed / (parcel length + gap)`` (one entry cannot pass parcels faster than the
wheels carry a parcel and the gap behind it), for the distributed sorter (``sort``), its central twin
(``central``: the same rules on one computer, greedy oldest-first grants) and the central reservation router
(``reserve``). Targets: distributed >= 80 % of the router; router >= 70 % of the kinematic bound.

Run: ``python benchmarks/bench_throughput.py [--duration S] [--controls sort central reserve] [scenario ...]``
(default: ``sorting_junction`` for 40 s and ``facility_40x40`` for 12 s; the facility takes minutes on a loaded
machine).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from virtual_vehicle.cells.programs import PROGRAMS
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report

DEFAULTS = {"sorting_junction": 40.0, "facility_40x40": 12.0}
CONTROLS = ("sort", "central", "reserve")


def saturated(name: str, control: str, duration: float):
    """The scenario with every entry saturated, under one of :data:`CONTROLS`."""
    sc, _ = load_scenario(name)
    if control == "central":
        options = sc.control.model_copy(update={"central": True})
    else:
        options = PROGRAMS[control].Options(**(sc.control.model_dump() | {"program": control}))
    # enough parcels that no entry runs dry (one a second, above any entry's bound): the scenario's mix repeated
    per_entry = len(sc.parcels) / len({(p.x, p.y) for p in sc.parcels})
    rounds = int(np.ceil(duration / per_entry))
    parcels = [p.model_copy(update={"name": f"{p.name}_{k}"}) for k in range(rounds) for p in sc.parcels]
    return sc.model_copy(update={"duration": duration, "arrivals": "saturate", "control": options,
                                 "parcels": parcels})


def measure(name: str, duration: float, controls=CONTROLS) -> dict:
    out = {}
    for control in controls:
        start = time.perf_counter()
        report = sorting_report(run(saturated(name, control, duration).build()))
        out[control] = (report, time.perf_counter() - start)
    return out


def show(name: str, duration: float, runs: dict) -> None:
    print(f"\n{name}: every entry saturated, {duration:g} s simulated")
    print(f"{'control':<9}{'entry (x, y) m':>16}{'fed':>5}{'out':>5}{'fed/h':>8}{'out/h':>8}{'bound/h':>9}"
          f"{'of bound':>10}")
    totals = {}
    for control, (report, wall) in runs.items():
        sat = report["saturation"]
        for e in sat["entries"]:
            out_h = "n/a" if e["delivered_per_hour"] is None else f"{e['delivered_per_hour']:.0f}"
            fed_h = "n/a" if e["fed_per_hour"] is None else f"{e['fed_per_hour']:.0f}"
            frac = "n/a" if e["fraction"] is None else f"{100 * e['fraction']:.0f} %"
            print(f"{control:<9}{'(%.2f, %.2f)' % (e['x'], e['y']):>16}{e['fed']:>5}{e['delivered']:>5}"
                  f"{fed_h:>8}{out_h:>8}{e['bound_per_hour']:>9.0f}{frac:>10}")
        t = sat["total"]
        totals[control] = t["delivered_per_hour"]
        frac = "n/a" if t["fraction"] is None else f"{100 * t['fraction']:.0f} %"
        out_h = "n/a" if t["delivered_per_hour"] is None else f"{t['delivered_per_hour']:.0f}"
        print(f"{control:<9}{'all entries':>16}{report['correct']:>5}{'':>5}{'':>8}{out_h:>8}"
              f"{t['bound_per_hour']:>9.0f}{frac:>10}   collisions {report['collisions']}, misrouted "
              f"{report['misrouted']}, lost {report['lost']}, wall {wall:.0f} s")
    if totals.get("sort") and totals.get("reserve"):
        print(f"distributed / reservation router: {100 * totals['sort'] / totals['reserve']:.0f} % (target >= 80 %)")
    if totals.get("central") and totals.get("reserve"):
        print(f"central sorter / reservation router: {100 * totals['central'] / totals['reserve']:.0f} %")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="*", default=list(DEFAULTS))
    parser.add_argument("--duration", type=float, default=None, help="simulated seconds (default per scenario)")
    parser.add_argument("--controls", nargs="+", choices=CONTROLS, default=list(CONTROLS))
    args = parser.parse_args()
    for name in args.scenarios:
        duration = args.duration or DEFAULTS.get(name, 30.0)
        show(name, duration, measure(name, duration, args.controls))


if __name__ == "__main__":
    main()
