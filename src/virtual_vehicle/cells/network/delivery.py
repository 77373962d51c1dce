"""Delivery models behind one interface: what was sent in one control tick and what has arrived by the next.

``exchange(outbox, t, period)`` takes the sentences cells send at tick time ``t`` (s) and returns the inbox the
programs read at ``t + period``, and a :class:`TickStats` of the traffic. Two models:

- :class:`IdealRounds`: every sentence sent on a connected port arrives at the next tick (vectorised; latency = one
  period), optionally with random loss.
- :class:`~virtual_vehicle.cells.network.wire.WireLevel`: the paper's hardware (one multiplexed RS232 port per cell,
  handshake lines, polling, bytes timed by the baud rate), where latency, queueing and loss emerge.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numba import njit

from virtual_vehicle.cells.network.messages import Mailbox, rows_any, rows_differ
from virtual_vehicle.cells.network.topology import Topology
from virtual_vehicle.model import state_data


@dataclass
class TickStats:
    """Traffic of one exchange. Per-cell arrays are (n,); latencies (s) are those of sentences delivered.

    ``lost``: sent but never arrived (a dead link or neighbour on ideal rounds, random loss); ``corrupted``: arrived
    but failed the sentence checks; ``undetected``: arrived corrupted but passed them; ``dropped``: given up by the
    sender (wire level: no answer after every attempt); ``unaddressed``: put on a port with no neighbour at all,
    which a cell can see, so it is not counted as sent."""

    sent: np.ndarray
    received: np.ndarray
    bytes_sent: np.ndarray
    bytes_received: np.ndarray
    latencies: np.ndarray
    lost: int = 0
    corrupted: int = 0
    undetected: int = 0
    dropped: int = 0
    unaddressed: int = 0
    extra: dict = field(default_factory=dict)


class Delivery(Protocol):
    topology: Topology

    def exchange(self, outbox: Mailbox, t: float, period: float) -> tuple[Mailbox, TickStats]:
        """Carry the sentences of ``outbox`` (sent at ``t``, s) over the links for one tick of ``period`` s; returns the
        inbox the cells read at the next tick and the tick's traffic statistics."""

    def set_topology(self, topology: Topology) -> None:
        """From now on carry sentences over ``topology`` (cells died, were taken out or snapped in, links cut)."""

    def to_data(self) -> dict:
        """What the delivery carries from one exchange to the next, as data (arrays and plain values)."""

    def load_data(self, d, inbox: Mailbox | None = None) -> None:
        """Go on from what :meth:`to_data` wrote, on a delivery made from the same setup and over the run's topology
        now; ``inbox`` is the mailbox the last exchange returned, which the run kept. Raises ValueError for data
        that is not such a delivery's."""


class IdealRounds:
    """Every sentence sent on a connected port arrives at the next tick; ``loss_rate`` drops each independently.

    Vectorised over all cells: one gather per word.
    """

    def __init__(self, topology: Topology, loss_rate: float = 0.0, seed: int | None = 0):
        if not 0.0 <= loss_rate <= 1.0:
            raise ValueError("loss_rate must be in [0, 1]")
        self.topology = topology
        self.loss_rate = loss_rate
        self.rng = np.random.default_rng(seed)
        self._last: dict | None = None  # what exchange_changed carried last

    def set_topology(self, topology: Topology) -> None:
        """From the next exchange on, deliver over ``topology`` (see :class:`Delivery`)."""
        self.topology = topology

    def to_data(self) -> dict:
        """The state of the delivery as data: its random generator's (``rng``). What :meth:`exchange_changed`
        carried last is a cache (the next call without it carries every sentence and compares, to the same inbox
        and statistics); the topology and loss rate are the setup's."""
        return {"rng": state_data.rng_to_data(self.rng)}

    def load_data(self, d, inbox: Mailbox | None = None) -> None:
        """Go on from what :meth:`to_data` wrote (on a delivery made from the same setup, over the run's topology
        now); ``inbox``: the mailbox the last exchange returned (unused: nothing of it is state here). Raises
        ValueError for other data."""
        d = state_data.fields(d, ("rng",), "delivery")
        self.rng = state_data.rng_from_data(d["rng"], "delivery.rng")
        self._last = None

    def exchange(self, outbox: Mailbox, t: float, period: float) -> tuple[Mailbox, TickStats]:
        """Every sentence on a connected port arrives at the next tick (each dropped with ``loss_rate``); see
        :class:`Delivery`."""
        topo = self.topology
        conn = topo.connected & topo.alive[:, None]
        src = np.where(conn, topo.neighbor, 0)
        back = np.where(conn, topo.back_port, 0)
        sending = outbox.present & topo.alive[:, None]
        arrives = conn & sending[src, back] & topo.alive[src]
        attempted = sending & (topo.neighbor >= 0)
        lost = int((attempted & ~topo.connected).sum())
        if self.loss_rate > 0:
            keep = self.rng.random(arrives.shape) >= self.loss_rate
            lost += int((arrives & ~keep).sum())
            arrives &= keep
        flat = src * outbox.present.shape[1] + back  # where each port's sentence comes from, in the flattened outbox
        inbox = Mailbox(outbox.schema, arrives, {k: np.where(arrives, np.take(v, flat), np.zeros((), v.dtype))
                                                 for k, v in outbox.values.items()})
        stats = _stats(outbox.schema, attempted.sum(axis=1), arrives.sum(axis=1), period, lost,
                       int((sending & (topo.neighbor < 0)).sum()))
        return inbox, stats

    def exchange_changed(self, outbox: Mailbox, changed: np.ndarray | None, t: float,
                         period: float) -> tuple[Mailbox, TickStats, np.ndarray | None]:
        """As :meth:`exchange`, for an outbox that differs from the one of the last call only in the rows ``changed``
        ((n,) bool): only what those cells sent is carried again, which gives the same inbox and statistics. Returns
        them and the (n,) cells whose inbox differs from the last call's. The inbox is this object's own and is
        updated in place by the next call. After the topology changed, at the first call and with random loss (whose
        draws must stay those of :meth:`exchange`), every sentence is carried and the inboxes are compared. With
        ``changed`` None (not known) every sentence is carried, nothing is compared, and None is returned for it."""
        topo, last = self.topology, self._last
        if changed is None:  # keep only the inbox, to compare the next call's with
            inbox, stats = self.exchange(outbox, t, period)
            self._last = {"topology": topo, "schema": outbox.schema, "inbox": inbox, "stale": True}
            return inbox, stats, None
        if (self.loss_rate > 0 or last is None or last["topology"] is not topo or last["schema"] != outbox.schema
                or "stale" in last):
            inbox, stats = self.exchange(outbox, t, period)
            before = None if last is None or last["schema"] != outbox.schema else last["inbox"]
            if before is None or before.present.shape != inbox.present.shape:
                inbox_changed = np.ones(len(inbox.present), dtype=bool)
            else:
                inbox_changed = rows_differ(before.arrays, inbox.arrays, len(inbox.present))
            sending = outbox.present & topo.alive[:, None]
            attempted = sending & (topo.neighbor >= 0)
            conn = topo.connected & topo.alive[:, None]
            self._last = {"topology": topo, "schema": outbox.schema, "inbox": inbox, "sending": sending,
                          "sent": stats.sent.copy(), "received": stats.received.copy(),
                          "lost": (attempted & ~topo.connected).sum(axis=1),
                          "unaddressed": (sending & (topo.neighbor < 0)).sum(axis=1),
                          "conn": conn, "src": np.where(conn, topo.neighbor, 0), "mutual": _mutual(topo)}
            return inbox, stats, inbox_changed
        rows = np.flatnonzero(changed)
        conn, src, inbox = last["conn"], last["src"], last["inbox"]
        P = inbox.present.shape[1]
        # the senders' rows first: what they send and attempt
        sending = last["sending"]
        sending[rows] = outbox.present[rows] & topo.alive[rows, None]
        nb = topo.neighbor[rows]
        last["sent"][rows] = (sending[rows] & (nb >= 0)).sum(axis=1)
        last["lost"][rows] = (sending[rows] & (nb >= 0) & ~topo.connected[rows]).sum(axis=1)
        last["unaddressed"][rows] = (sending[rows] & (nb < 0)).sum(axis=1)
        # then the cells that hear any of them: their whole inbox again, as exchange gathers it. They are among
        # the senders' neighbours (links go both ways: checked once a topology), so only those are looked at
        if last["mutual"] and len(rows) * 8 < len(changed):
            near = topo.neighbor[rows]
            near = np.unique(near[near >= 0])
            dest = near[rows_any(changed[src[near]] & conn[near])]
        else:
            dest = np.flatnonzero(rows_any(changed[src] & conn))
        s, b = src[dest], np.where(conn[dest], topo.back_port[dest], 0)
        arrives = conn[dest] & sending[s, b] & topo.alive[s]
        flat = s * P + b
        inbox_changed = np.zeros(len(changed), dtype=bool)
        inbox_changed[dest] = rows_any(inbox.present[dest] != arrives)
        inbox.present[dest] = arrives
        for k, v in inbox.values.items():  # each word's rows of the cells that hear again (the same dtype)
            _carry(v, outbox.values[k].reshape(-1), dest, flat, arrives, inbox_changed)
        last["received"][dest] = arrives.sum(axis=1)
        stats = _stats(outbox.schema, last["sent"].copy(), last["received"].copy(), period, int(last["lost"].sum()),
                       int(last["unaddressed"].sum()))
        return inbox, stats, inbox_changed


def _mutual(topo: Topology) -> bool:
    """Whether every link of ``topo`` goes both ways: the neighbour on port q of cell i has i on its port
    ``back_port[i, q]``."""
    cells, ports = np.nonzero(topo.neighbor >= 0)
    back = topo.back_port[cells, ports]
    return bool((back >= 0).all() and (topo.neighbor[topo.neighbor[cells, ports], back] == cells).all())


@njit(cache=True)
def _carry(inbox, sent, dest, flat, arrives, changed):
    """Port q of cell ``dest[a]`` hears ``sent[flat[a, q]]`` (the senders' words, flattened) where ``arrives[a, q]``,
    else 0, written into ``inbox`` in place; ``changed[dest[a]]`` set where that differs from what it held. The
    array operations it replaces (take, where, compare, write back) took ~50 us a word a tick on 10^4 cells."""
    zero = inbox.dtype.type(0)
    for a in range(dest.shape[0]):
        i = dest[a]
        for q in range(inbox.shape[1]):
            new = sent[flat[a, q]] if arrives[a, q] else zero
            if inbox[i, q] != new:
                changed[i] = True
            inbox[i, q] = new


def _stats(schema, sent: np.ndarray, received: np.ndarray, period: float, lost: int, unaddressed: int) -> TickStats:
    """Ideal rounds' traffic: every sentence delivered took one period."""
    size = schema.sentence_bytes
    return TickStats(sent, received, sent * size, received * size, np.full(int(received.sum()), period), lost=lost,
                     unaddressed=unaddressed)
