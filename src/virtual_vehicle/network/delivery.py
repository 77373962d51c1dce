"""Delivery models behind one interface: what was sent in one control tick and what has arrived by the next.

``exchange(outbox, t, period)`` takes the sentences cells send at tick time ``t`` (s) and returns the inbox the
programs read at ``t + period``, and a :class:`TickStats` of the traffic. Two models:

- :class:`IdealRounds`: every sentence sent on a connected port arrives at the next tick (vectorised; latency = one
  period), optionally with random loss.
- :class:`~virtual_vehicle.network.wire.WireLevel`: the paper's hardware (one multiplexed RS232 port per cell,
  handshake lines, polling, bytes timed by the baud rate), where latency, queueing and loss emerge.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .messages import Mailbox
from .topology import Topology


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

    def set_topology(self, topology: Topology) -> None:
        """From the next exchange on, deliver over ``topology`` (see :class:`Delivery`)."""
        self.topology = topology

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
        size = outbox.schema.sentence_bytes
        sent = attempted.sum(axis=1)
        received = arrives.sum(axis=1)
        stats = TickStats(sent, received, sent * size, received * size, np.full(int(received.sum()), period),
                          lost=lost, unaddressed=int((sending & (topo.neighbor < 0)).sum()))
        return inbox, stats
