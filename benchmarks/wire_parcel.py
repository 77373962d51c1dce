"""What one parcel's ride costs over a slow wire (issue 33: the sorter at 9600 baud). Prints figures; asserts
nothing.

``sorting_junction`` (or ``--scenario``) with its first parcel only, run on ideal rounds and over the wire model at
each ``--baud`` (``--cts``: the wire's handshake timeout, s), tick by tick. Per run:

- ``d <2 s``, ``d >2 s``: the gradient words ``d`` a cell changed on a port in the first 2 s (the gradients
  forming) and after (they form again: neighbours whose heartbeats were given up on a busy line stop being
  trusted, and the gradients re-form without them, then with them), and ``last d`` when the last changed (s);
- ``start``: when the parcel first moves (speed above 0.05 m/s), ``out`` when it left the array (or ``-``);
- ``stands``: the spells it stands still (below 0.01 m/s for at least 0.1 s) between start and delivery (or the
  run's end), their number and total time (s): a vehicle stands when its front cells hear a run of held cells
  ahead shorter than ``gap``, so on a slow wire the refill of that run after each step shows here;
- ``turns``: reversals of its heading (two moves more than 150 degrees apart) - a vehicle that runs past its exit
  lane before its cells agree to turn comes back;
- ``path``: the length of its path (m), against the ideal run's;
- the sentences sent, given up (``dropped``) and their mean latency (s).

Run: ``python benchmarks/wire_parcel.py [--duration 30] [--baud 9600 115200] [--cts 0.002] [--seed 0]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.run.sim import network_job


def ride(sc) -> dict:
    """Run ``sc`` tick by tick; the figures of the module notes."""
    job = network_job(sc.build())
    period = job.period
    changes = []  # (tick, d words changed)
    last = None
    start = time.perf_counter()
    while not job.done:
        d = job.state["said"]["d"].copy()
        if last is not None:
            changes.append((job.k, int((d != last).sum())))
        last = d
        job.tick()
    wall = time.perf_counter() - start
    res = job.result()
    ticks = np.array([k for k, c in changes], dtype=float) * period
    counts = np.array([c for _, c in changes])
    early = int(counts[ticks < 2.0].sum())
    late = int(counts[ticks >= 2.0].sum())
    last = float(ticks[counts > 0][-1]) if counts.any() else 0.0
    tr = res.parcels[0].trajectory
    t, xy = tr.times, tr.states[:, :2]
    v = np.hypot(tr.states[:, 3], tr.states[:, 4])
    moving = np.flatnonzero(v > 0.05)
    t_start = float(t[moving[0]]) if len(moving) else None
    ended = tr.status != "completed" or tr.t_end < sc.duration - 1e-9
    t_out = float(tr.t_end) if ended else None
    spells = []
    if t_start is not None:
        still = (v < 0.01) & (t >= t_start) & (t <= (t_out if t_out is not None else t[-1]))
        k = 0
        while k < len(t):
            if still[k]:
                j = k
                while j + 1 < len(t) and still[j + 1]:
                    j += 1
                if t[j] - t[k] >= 0.1:
                    spells.append(float(t[j] - t[k]))
                k = j + 1
            else:
                k += 1
    step = np.diff(xy, axis=0)
    big = step[np.hypot(step[:, 0], step[:, 1]) > 1e-3]
    unit = big / np.hypot(big[:, 0], big[:, 1])[:, None]
    turns = int((np.sum(unit[1:] * unit[:-1], axis=1) < np.cos(np.radians(150))).sum()) if len(unit) > 1 else 0
    net = res.network
    lat = net.latency.mean
    return {"early": early, "late": late, "last": last, "start": t_start, "out": t_out, "stands": len(spells),
            "standing": sum(spells), "turns": turns, "path": float(np.hypot(step[:, 0], step[:, 1]).sum()),
            "sent": int(net.per_tick["sent"].sum()), "dropped": int(net.per_tick["dropped"].sum()),
            "latency": lat, "wall": wall}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="sorting_junction")
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--baud", type=float, nargs="*", default=[9600.0, 115200.0])
    parser.add_argument("--cts", type=float, default=None, help="the wire's cts_timeout (s; default the scenario's)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    sc, _ = load_scenario(args.scenario)
    sc = sc.model_copy(update={"duration": args.duration, "parcels": sc.parcels[:1]})

    def variant(**update):
        return sc.model_copy(update={"control": sc.control.model_copy(update=update)})

    print(f"{args.scenario}, its first parcel alone, {args.duration:g} s")
    print(f"{'run':<22}{'d <2 s':>7}{'d >2 s':>7}{'last d':>7}{'start':>7}{'out':>7}{'stands':>7}{'stood':>7}"
          f"{'turns':>6}{'path':>7}{'sent':>8}{'dropped':>8}{'latency':>8}{'wall':>6}")
    runs = [("ideal rounds", variant(delivery="ideal", seed=args.seed))]
    for baud in args.baud:
        wire = {"baud": baud} | ({} if args.cts is None else {"cts_timeout": args.cts})
        runs.append((f"wire {baud:g} baud", variant(delivery="wire", seed=args.seed,
                                                    wire=sc.control.wire.model_copy(update=wire))))
    for label, variant_sc in runs:
        r = ride(variant_sc)

        def f(x, w=7):
            return f"{x:>{w}.2f}" if x is not None else f"{'-':>{w}}"

        print(f"{label:<22}{r['early']:>7}{r['late']:>7}{f(r['last'])}{f(r['start'])}{f(r['out'])}"
              f"{r['stands']:>7}{f(r['standing'])}{r['turns']:>6}{f(r['path'])}{r['sent']:>8}{r['dropped']:>8}"
              f"{f(r['latency'], 8) if r['latency'] is not None else '       -'}{r['wall']:>6.0f}", flush=True)


if __name__ == "__main__":
    main()
