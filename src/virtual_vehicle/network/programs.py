"""Cell programs and the multi-hop primitives they are built from.

The contract (one program runs on every cell; written once, vectorised over cells):

- ``schema``: the words of the sentences the program sends (:class:`~virtual_vehicle.network.messages.Schema`).
- ``init(n, ports, config) -> state``: per-cell state, a dict of arrays whose first axis is the cell.
- ``step(state, inputs) -> (state, outbox, wheel_speeds)``: one control tick. ``inputs`` is a :class:`CellInputs`;
  ``outbox`` a Mailbox (what each cell sends on each port); ``wheel_speeds`` (n, 2) the surface speed of each cell's
  two wheels along their own drive directions, m/s.

Row i of every input is cell i's own: its sensors, its state, the sentences that arrived on its ports, which of its
ports lead to a neighbour, and its local configuration (set when it was installed, e.g. "I am an exit"). A program
must compute row i of its outputs from row i of its inputs only: no cell has an address, knows its position, or sees
another cell's state except through sentences. :func:`check_program` tests a program against this contract.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .messages import Mailbox, Schema
from .sentence import WordType

UNREACHABLE = 255
"""Hop distance meaning "no path known" (the largest U8)."""


@dataclass
class CellInputs:
    """What every cell sees at a tick. Arrays have one row per cell.

    Attributes:
        t: time of the tick, s (each cell's own clock; all clocks agree here).
        sensors: (n, S) presence readings, 1 where a parcel covers the sensor.
        inbox: sentences that arrived since the last tick, per port.
        connected: (n, P) ports that lead to a neighbour (a cell can tell whether a neighbour is plugged in).
        config: per-cell local configuration, arrays by name.
        labels: (n,) the label (e.g. destination) a reader in the cell sees on the parcel above it, -1 for none;
            None when the run has no labelled parcels. Programs read it only where a reader is installed.
    """

    t: float
    sensors: np.ndarray
    inbox: Mailbox
    connected: np.ndarray
    config: dict = field(default_factory=dict)
    labels: np.ndarray | None = None


class CellProgram(Protocol):
    schema: Schema

    def init(self, n: int, ports: int, config: dict) -> dict:
        """Per-cell state for ``n`` cells with ``ports`` links each, as a dict of arrays with first axis n (``config``
        is the scenario's [control.config] table)."""

    def step(self, state: dict, inputs: CellInputs) -> tuple[dict, Mailbox, np.ndarray]:
        """One control tick for all cells at once, each using only its own row of ``state`` and ``inputs`` (its sensors,
        its inbox from its neighbours, its links): returns the new state, the outbox (a sentence per port) and the (n,
        2) wheel speeds, m/s along each cell's drive directions."""


# --------------------------------------------------------------------------- primitives (pure, vectorised)

def gradient_update(dist_in: np.ndarray, present: np.ndarray, is_source: np.ndarray, cap: int = UNREACHABLE) -> np.ndarray:
    """Distance-vector step: a source is at 0; any other cell is one more than the smallest distance it currently
    trusts from a neighbour (``present``), or ``cap`` (unreachable) if none is below cap - 1. Trusting only recent
    sentences makes the field re-converge when a cell or link dies (distances climb until they meet the new
    shortest path or ``cap``)."""
    heard = np.where(present, dist_in.astype(np.int64), cap)
    best = heard.min(axis=1) if heard.shape[1] else np.full(len(is_source), cap)
    return np.where(is_source, 0, np.minimum(best + 1, cap)).astype(np.int64)


def flood_update(seq: np.ndarray, value: np.ndarray, hops: np.ndarray, in_seq: np.ndarray, in_value: np.ndarray,
                 in_hops: np.ndarray, present: np.ndarray, limit: int):
    """Hop-limited flood: a cell adopts the newest sentence (highest sequence number; fewest hops on a tie) heard
    on any port if it is newer than what it holds, one hop further. Returns new (seq, value, hops, adopted)."""
    s = np.where(present, in_seq.astype(np.int64), -1)
    h = np.where(present, in_hops.astype(np.int64), 1 << 30)
    key = s * (1 << 31) - h  # highest seq, then fewest hops
    port = np.argmax(key, axis=1)
    rows = np.arange(len(seq))
    best_seq, best_hops = s[rows, port], h[rows, port]
    adopt = (best_seq > seq) & (best_hops < limit)
    new_seq = np.where(adopt, best_seq, seq)
    new_val = np.where(adopt, in_value[rows, port], value)
    new_hops = np.where(adopt, best_hops + 1, hops)
    return new_seq, new_val, new_hops, adopt


def descend_port(dist_in: np.ndarray, present: np.ndarray, own: np.ndarray) -> np.ndarray:
    """For forwarding along a gradient: the port whose neighbour reported the smallest distance, if it is smaller
    than the cell's own; -1 where no neighbour is closer (the cell is a source or cut off)."""
    heard = np.where(present, dist_in.astype(np.int64), np.iinfo(np.int64).max)
    port = np.argmin(heard, axis=1)
    closer = heard[np.arange(len(own)), port] < own
    return np.where(closer, port, -1)


# --------------------------------------------------------------------------- programs

class Routing:
    """Gradient to the exits plus packet forwarding (a multi-hop demonstration program; wheels stay stopped).

    Config: ``exit`` (n,) bool — cells where packets are delivered; ``packet`` (n,) int16 — a packet (its value) a
    cell holds at the start, -1 for none. Each tick every cell broadcasts its hop distance to the nearest exit; a
    cell holding packets forwards one (value, hop count) on the port of its closest neighbour. Delivered packets are
    recorded in ``state["delivered"]`` (value, hops) at the exit cell.

    A neighbour's distance is trusted for ``max_age`` ticks after it was last heard: on ideal rounds every neighbour
    is heard every tick, but on a real (wire-level) network a busy link may deliver only now and then.
    """

    schema = Schema.of(dist=(1, WordType.U8), pkt=(2, WordType.I16), pkt_hops=(3, WordType.U8))

    def __init__(self, max_age: int = 0):
        self.max_age = int(max_age)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each."""
        packets = np.asarray(config.get("packet", np.full(n, -1)), dtype=np.int64)
        return {"dist": np.full(n, UNREACHABLE, dtype=np.int64),
                "heard": np.full((n, ports), UNREACHABLE, dtype=np.int64),
                "age": np.full((n, ports), np.iinfo(np.int32).max, dtype=np.int64),
                "carry": [[(int(v), 0)] if v >= 0 else [] for v in packets],
                "delivered": [[] for _ in range(n)]}

    def step(self, state, inputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds,
        m/s."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        exits = np.asarray(inputs.config.get("exit", np.zeros(n, bool)), dtype=bool)
        heard = np.where(inbox.present, inbox.values["dist"], state["heard"])
        age = np.where(inbox.present, 0, np.minimum(state["age"] + 1, np.iinfo(np.int32).max))
        trusted = age <= self.max_age
        dist = gradient_update(heard, trusted, exits)
        carry = state["carry"]
        delivered = state["delivered"]
        # take custody of packets that arrived
        got = inbox.present & (inbox.values["pkt"] >= 0)
        for i, p in zip(*np.nonzero(got)):
            carry[i].append((int(inbox.values["pkt"][i, p]), int(inbox.values["pkt_hops"][i, p])))
        for i in np.flatnonzero(exits):
            delivered[i].extend(carry[i])
            carry[i] = []
        out = Mailbox.broadcast(self.schema, np.ones(n, bool), P, dist=np.minimum(dist, UNREACHABLE),
                                pkt=np.full(n, -1), pkt_hops=np.zeros(n))
        port = descend_port(heard, trusted, dist)
        for i in np.flatnonzero((port >= 0) & np.array([len(c) > 0 for c in carry])):
            value, hops = carry[i].pop(0)
            out.values["pkt"][i, port[i]] = value
            out.values["pkt_hops"][i, port[i]] = hops + 1
        return ({"dist": dist, "heard": heard, "age": age, "carry": carry, "delivered": delivered}, out,
                np.zeros((n, 2)))


class Flood:
    """Hop-limited flood of a value from the cells whose config ``origin`` is set (wheels stay stopped)."""

    schema = Schema.of(seq=(1, WordType.U16), value=(2, WordType.I16), hops=(3, WordType.U8))

    def __init__(self, limit: int):
        self.limit = int(limit)

    def init(self, n, ports, config):
        """Fresh per-cell state arrays for ``n`` cells with ``ports`` links each."""
        origin = np.asarray(config.get("origin", np.zeros(n, bool)), dtype=bool)
        return {"seq": np.where(origin, 1, 0), "value": np.where(origin, np.asarray(config.get("value", 0)), 0),
                "hops": np.zeros(n, dtype=np.int64), "fresh": origin.copy()}

    def step(self, state, inputs):
        """One control tick for every cell at once: new state, the sentences to send, and the (n, 2) wheel speeds,
        m/s."""
        inbox = inputs.inbox
        n, P = inbox.present.shape
        seq, value, hops, adopted = flood_update(state["seq"], state["value"], state["hops"], inbox.values["seq"],
                                                 inbox.values["value"], inbox.values["hops"], inbox.present,
                                                 self.limit)
        send = (adopted | state["fresh"]) & (hops < self.limit)  # relay what is new, in the tick it arrives
        out = Mailbox.broadcast(self.schema, send, P, seq=seq, value=value, hops=hops)
        return {"seq": seq, "value": value, "hops": hops, "fresh": np.zeros(n, bool)}, out, np.zeros((n, 2))


# --------------------------------------------------------------------------- contract checker

def check_program(program: CellProgram, topology, config: dict, ticks: int = 5, seed: int = 0,
                  sensors: np.ndarray | None = None) -> None:
    """Check a program against the cell-program contract on ``topology`` (ideal rounds): the output shapes and
    dtypes are right, the program is deterministic, and it is local: relabelling the cells (permuting ids, and the
    topology, configuration and ``sensors`` readings with them) relabels its outputs exactly. ``sensors``: (n, S)
    readings held for every tick (default: nothing seen). Raises AssertionError."""
    from .delivery import IdealRounds
    from .topology import Topology

    n, P = topology.n, topology.ports
    perm = np.random.default_rng(seed).permutation(n)
    inv = np.argsort(perm)
    # cell perm[k] of the original is cell k of the relabelled array
    nb = topology.neighbor[perm]
    relabelled = Topology(np.where(nb >= 0, inv[np.maximum(nb, 0)], -1), topology.back_port[perm],
                          topology.link_up[perm], topology.alive[perm])
    pconfig = {k: np.asarray(v)[perm] for k, v in config.items()}
    seen = np.zeros((n, 1), bool) if sensors is None else np.asarray(sensors, dtype=bool)

    def run(topo, cfg, seen):
        state = program.init(n, P, cfg)
        inbox = Mailbox.empty(program.schema, n, P)
        delivery = IdealRounds(topo)
        trace = []
        for k in range(ticks):
            inputs = CellInputs(k * 0.01, seen, inbox, topo.connected, cfg)
            state, out, wheels = program.step(state, inputs)
            assert out.present.shape == (n, P) and wheels.shape == (n, 2), "outputs must be (n, P) and (n, 2)"
            for f in program.schema.fields:
                assert out.values[f.name].shape == (n, P)
            trace.append((out.present.copy(), {k2: v.copy() for k2, v in out.values.items()}, np.array(wheels)))
            inbox, _ = delivery.exchange(out, k * 0.01, 0.01)
        return trace

    a = run(topology, config, seen)
    again = run(topology, config, seen)
    b = run(relabelled, pconfig, seen[perm])
    for (pa, va, wa), (pa2, va2, wa2), (pb, vb, wb) in zip(a, again, b):
        assert np.array_equal(pa, pa2) and np.array_equal(wa, wa2), "the program is not deterministic"
        assert np.array_equal(pa[perm], pb), "sending depends on cell ids: the program is not local"
        assert np.array_equal(wa[perm], wb), "wheel speeds depend on cell ids: the program is not local"
        for name in va:
            assert np.array_equal(np.where(pa, va[name], 0)[perm], np.where(pb, vb[name], 0)), \
                f"word {name!r} depends on cell ids: the program is not local"
