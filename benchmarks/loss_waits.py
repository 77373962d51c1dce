"""What the sorter's waiting cells wait on under sentence loss (issue 33: 10 % loss, >= 95 % of the fault-free
deliveries): ``sorting_junction`` (or ``--scenario``) run tick by tick on ideal rounds at ``--loss``; at every tick
each front cell of a standing vehicle (it carries the vehicle, its direction leads to a neighbour that does not,
and the vehicle's stop reaches it) is classified by the handshake with the cell ahead, comparing what each of the
two has said last (its ``said`` words on that port) with what the other holds of it (heard, or arriving this tick):

- ``request lost``: the cell ahead does not hold the request (``req``, ``rdep``) the front cell says;
- ``grant lost``: the front cell does not hold the cell ahead's latest ``hold``, ``ack``, ``stop`` or ``key``;
- ``other word lost``: the front cell misses another of the cell ahead's words (``d``, ``vid``, ``blk``, ...);
- ``in step``: both hold the other's latest words - the vehicle waits on traffic (the cell ahead held for an
  older one, or its run not yet deep enough), not on a loss;
- ``untrusted``: the front cell no longer trusts the cell ahead (nothing heard for ``trust`` ticks).

A loss keeps a cell out of step until a repeat or the heartbeat arrives (or an ask is answered); the instrument
counts those cell-ticks, the stale words, and the out-of-step spells by length (ticks), so that a few long spells
(a change lost in every repeat, repaired by the heartbeat) show apart from many one-tick ones (a lost sentence whose
repeat arrives next). Also the delivered parcels, the sentences sent and the asks. Prints figures; asserts nothing.

Run: ``python benchmarks/loss_waits.py [--loss 0.1] [--seed 0] [--duration 40] [--scenario sorting_junction]``.
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np

GRANT = ("hold", "ack", "stop", "key")
REQUEST = ("req", "rdep")


def classify(job, program) -> list[tuple[int, str, tuple[str, ...]]]:
    """The standing front cells of the run ``job`` at the start of its next tick: (cell, class, stale words) each
    (see the module notes)."""
    from virtual_vehicle.cells.sorting.policy import ASK
    from virtual_vehicle.cells.sorting.rules import hop_bits, opposite

    st, inbox, topo = job.state, job.inbox, job.topology
    n, P = topo.n, topo.ports
    none = (1 << hop_bits(P)) - 1
    nb = topo.neighbor
    tick = job.k
    vid, direction, stop = st["vid"], st["dir"], st["stop"]
    out = []
    for i in np.nonzero((vid >= 0) & (direction >= 0) & ((stop & none) <= program.reach))[0]:
        d = int(direction[i])
        j = int(nb[i, d])
        if j < 0 or vid[j] == vid[i] or not topo.connected[i, d]:
            continue  # not a front cell, or one at the array's edge (an exit)
        r = opposite(d, P)

        def holds(a, port, b, bport, word):
            """Whether cell ``a`` holds (or hears this tick) the word cell ``b`` last said to it."""
            said = int(st["said"][word][b, bport])
            if inbox.present[a, port]:
                got = int(inbox.values[word][a, port])
                got = got - ASK if word == "ex" and got >= ASK // 2 else got
            else:
                got = int(st["heard"][word][a, port])
            return got == said

        if tick - st["heard_at"][i, d] > program.trust and not inbox.present[i, d]:
            out.append((int(i), "untrusted", ()))
            continue
        lost_req = tuple(w for w in REQUEST if not holds(j, r, i, d, w))
        lost_in = tuple(w for w in st["said"] if w not in REQUEST and not holds(i, d, j, r, w))
        if lost_req:
            out.append((int(i), "request lost", lost_req + lost_in))
        elif any(w in GRANT for w in lost_in):
            out.append((int(i), "grant lost", lost_in))
        elif lost_in:
            out.append((int(i), "other word lost", lost_in))
        else:
            out.append((int(i), "in step", ()))
    return out


def measure(scenario: str, loss: float, seed: int, duration: float) -> dict:
    """Run ``scenario`` for ``duration`` s at sentence loss ``loss`` (network seed ``seed``), classifying the
    waiting cells every tick; the counts."""
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import network_job
    from virtual_vehicle.run.tasks import sorting_report

    sc, _ = load_scenario(scenario)
    sc = sc.model_copy(update={"duration": duration, "control": sc.control.model_copy(
        update={"delivery": "ideal", "loss_rate": loss, "seed": seed})})
    setup = sc.build()
    job = network_job(setup)
    program = setup.control.program
    ticks = Counter()
    words = Counter()
    spells = Counter()  # out-of-step spells (request or grant or other word lost) by length, ticks
    running: dict[int, int] = {}  # cell -> ticks out of step so far
    asks = 0
    while not job.done:
        seen = classify(job, program)
        now = {}
        for i, kind, stale in seen:
            ticks[kind] += 1
            words.update(stale)
            if kind.endswith("lost"):
                now[i] = running.get(i, 0) + 1
        for i, length in running.items():
            if i not in now:
                spells[length] += 1
        running = now
        job.tick()
        asks += int((job.inbox.present & (job.inbox.values["ex"] >= (1 << 13))).sum())
    for length in running.values():
        spells[length] += 1
    rep = sorting_report(job.result())
    sent = int(job.per_tick["sent"].sum())
    return {"ticks": ticks, "words": words, "spells": spells, "asks": asks, "sent": sent,
            "correct": rep["correct"], "collisions": rep["collisions"], "misrouted": rep["misrouted"],
            "lost": rep.get("lost", 0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="sorting_junction")
    parser.add_argument("--loss", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=40.0)
    args = parser.parse_args()
    res = measure(args.scenario, args.loss, args.seed, args.duration)
    print(f"{args.scenario}, {args.duration:g} s, {args.loss:.0%} loss, seed {args.seed}: {res['correct']} delivered "
          f"correctly, {res['collisions']} collisions, {res['misrouted']} misrouted, {res['lost']} lost; "
          f"{res['sent']} sentences sent ({res['sent'] / args.duration:.0f}/s), {res['asks']} asks arrived")
    total = sum(res["ticks"].values()) or 1
    print("standing front cells, cell-ticks by what they wait on:")
    for kind in ("in step", "request lost", "grant lost", "other word lost", "untrusted"):
        print(f"  {kind:<16}{res['ticks'][kind]:>8}{res['ticks'][kind] / total:>8.1%}")
    print("stale words (cell-ticks):", ", ".join(f"{w} {c}" for w, c in res["words"].most_common()))
    lengths = sorted(res["spells"].elements())
    if lengths:
        long = [x for x in lengths if x > 3]
        print(f"out-of-step spells: {len(lengths)}, {sum(lengths)} cell-ticks; 1 tick {res['spells'][1]}, "
              f"2-3 ticks {res['spells'][2] + res['spells'][3]}, longer {len(long)} ({sum(long)} cell-ticks, "
              f"longest {lengths[-1]})")


if __name__ == "__main__":
    main()
