"""The distributed sorter over slow and lossy links (issue 33: 9600 baud and 10 % loss). Prints figures; asserts
nothing.

``sorting_junction`` (or ``--scenario``) run on ideal rounds, on ideal rounds with 10 % sentence loss, and over the
wire model at each ``--baud``: parcels delivered correctly and the share of the ideal run's, the first delivery and
its ratio to the ideal run's, collisions and misroutes, and the line's budget: sentences a second on the busiest
link and on average per linked port, the bits they take against the line rate (``load``: bits sent a second over
the baud, both directions sharing one port), sentences the sender gave up on (``dropped``) and the wall time.

``--stream``: instead of the scenario's own parcels, ``sorting_junction`` fed a parcel every 3 s for the whole
``--duration`` (the stream of ``long_run.py``), so that the deliveries measure throughput over a run long enough that
one parcel due at the cut is a small share (at the junction's own 40 s one parcel is 7.7 % of 13).

Run: ``python benchmarks/bench_wire_sorter.py [--duration 40] [--baud 9600 115200] [--seeds 0] [--stream]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import sorting_report


def one(sc, label: str, ideal: dict | None) -> dict:
    """Run ``sc``; print and return its figures, against the ``ideal`` run's when given."""
    start = time.perf_counter()
    res = run(sc.build())
    wall = time.perf_counter() - start
    rep = sorting_report(res)
    firsts = [r["entered_at_s"] + r["delivery_time_s"] for r in rep["parcels"]
              if r["outcome"] == "delivered" and r["correct"]]
    first = min(firsts) if firsts else None
    net = res.network
    duration = float(net.per_tick["t"][-1] + net.period) if len(net.per_tick["t"]) else sc.duration
    topo = res.setup.control.topology
    links = int(topo.connected.sum())  # linked ports (each link counted from both ends)
    per_cell = net.per_cell["cell_sent"] / duration
    ports = np.maximum(topo.connected.sum(axis=1), 1)
    bits = net.per_cell["cell_bytes_sent"] * 10 / duration  # 10 bits a byte on the line (start, 8 data, stop)
    baud = sc.control.wire.baud
    out = {"correct": rep["correct"], "first": first, "collisions": rep["collisions"], "misrouted": rep["misrouted"],
           "sent_per_s": float(net.per_tick["sent"].sum() / duration),
           "per_port_mean": float(net.per_tick["sent"].sum() / duration / links),
           "per_port_max": float((per_cell / ports).max()),
           "cell_bits_max": float(bits.max()), "dropped": int(net.per_tick["dropped"].sum())}
    share = f"{out['correct'] / ideal['correct']:6.0%}" if ideal and ideal["correct"] else "     -"
    ratio = f"{first / ideal['first']:5.2f}x" if ideal and first and ideal["first"] else "     -"
    load = f"{out['cell_bits_max'] / baud:6.1%}" if sc.control.delivery == "wire" else "     -"
    print(f"{label:<24}{out['correct']:>4}{share:>8}{(first or float('nan')):>8.2f}{ratio:>8}"
          f"{out['collisions']:>4}{out['misrouted']:>4}{out['sent_per_s']:>9.0f}{out['per_port_mean']:>8.1f}"
          f"{out['per_port_max']:>8.1f}{load:>8}{out['dropped']:>8}{wall:>8.0f}", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="sorting_junction")
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--baud", type=float, nargs="*", default=[9600.0, 115200.0])
    parser.add_argument("--seeds", type=int, nargs="*", default=[0], help="the network's seeds (wire and loss)")
    parser.add_argument("--loss", type=float, default=0.1, help="sentence loss on ideal rounds (0: skip)")
    parser.add_argument("--skip-ideal", action="store_true", help="no ideal run (no shares then)")
    parser.add_argument("--stream", action="store_true", help="sorting_junction fed a parcel every 3 s throughout")
    args = parser.parse_args()
    if args.stream:
        from long_run import hour_scenario  # (this folder's: the junction's stream)

        sc = hour_scenario(args.duration / 60.0)
    else:
        sc, _ = load_scenario(args.scenario)
        sc = sc.model_copy(update={"duration": args.duration})
    print(f"{sc.name if args.stream else args.scenario}, {args.duration:g} s")
    print(f"{'run':<24}{'ok':>4}{'share':>8}{'first':>8}{'ratio':>8}{'col':>4}{'mis':>4}{'sent/s':>9}"
          f"{'/port':>8}{'max':>8}{'load':>8}{'dropped':>8}{'wall':>8}")

    def variant(**update):
        return sc.model_copy(update={"control": sc.control.model_copy(update=update)})

    ideal = None if args.skip_ideal else one(variant(delivery="ideal"), "ideal rounds", None)
    for seed in args.seeds:
        if args.loss > 0:
            one(variant(delivery="ideal", loss_rate=args.loss, seed=seed), f"ideal, {args.loss:.0%} loss, s{seed}",
                ideal)
        for baud in args.baud:
            one(variant(delivery="wire", seed=seed, wire=sc.control.wire.model_copy(update={"baud": baud})),
                f"wire {baud:g} baud, s{seed}", ideal)


if __name__ == "__main__":
    main()
