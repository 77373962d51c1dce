"""Every cell controller on its own clock: crystal drift per cell, jitter per tick, and mailboxes read by time.

A real cell's controller ticks on its own oscillator, not on a clock shared with the array. Cell i's k-th tick falls
at ``k * period * (1 + d_i) + e_ik`` (s), where ``d_i`` (the crystal's rate error) is drawn once per cell from
U(-drift, drift) and ``e_ik`` (interrupt latency, a late timer) per tick from U(0, jitter); every cell ticks first at
0. Instants are placed on a grid of ``slots`` per period (the first grid instant at or after the tick), so that cells
that tick at the same instant step together: the run goes from one instant where some cell ticks to the next, and
with no drift and no jitter every cell ticks at every k * period, one group of all cells, the synchronous run.

Sentences go into the receiver's mailbox (:class:`Mailboxes`), one place per port: a cell reads at its own tick what
arrived since its last tick and empties it; a sentence that arrives before the receiver read the one before replaces
it (a neighbour whose clock runs fast overwrites one in a hundred at 1 % drift), and a port with nothing new reads
empty (one in a hundred from a slow neighbour). Units: s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.model import state_data


@dataclass(frozen=True)
class ClockParams:
    """The cells' clocks: ``drift`` (the largest relative rate error, 0..0.1: 0.01 is +-1 %), ``jitter`` (s, the
    largest lateness of a tick, below half the period), ``seed`` (of the drifts and jitters) and ``slots`` (grid
    instants a period that ticks are placed on, 1..1000)."""

    drift: float = 0.0
    jitter: float = 0.0
    seed: int = 0
    slots: int = 20

    @property
    def synchronous(self) -> bool:
        """Whether every cell ticks on one shared clock (no drift, no jitter)."""
        return self.drift == 0 and self.jitter == 0

    def check(self, period: float) -> None:
        """Raises ValueError for clocks that do not fit ``period`` (s): two ticks of a cell must never fall on one
        grid instant."""
        if not 0 <= self.drift <= 0.1:
            raise ValueError(f"drift must be in [0, 0.1], got {self.drift}")
        if not 0 <= self.jitter < period / 2:
            raise ValueError(f"jitter must be in [0, period / 2) = [0, {period / 2:g}) s, got {self.jitter}")
        if not (type(self.slots) is int and 1 <= self.slots <= 1000):
            raise ValueError(f"slots must be an integer in [1, 1000], got {self.slots}")


class CellClocks:
    """The clocks of ``n`` cells with control ``period`` (s): which cells tick next and when.

    Time is counted in grid instants (``period / slots`` s each); :meth:`next` names the next instant some cell
    ticks at and those cells, :meth:`advance` schedules their next tick."""

    def __init__(self, n: int, period: float, params: ClockParams):
        params.check(period)
        self.n, self.period, self.p = n, float(period), params
        self.m = params.slots
        self.rng = np.random.default_rng(params.seed)
        self.rate = 1.0 + (self.rng.uniform(-params.drift, params.drift, n) if params.drift > 0 else np.zeros(n))
        """(n,) each cell's period over the nominal one: 1 + d_i."""
        self.count = np.zeros(n, dtype=np.int64)  # ticks each cell has taken
        self.slot = np.zeros(n, dtype=np.int64)  # the grid instant of each cell's next tick

    def time_of(self, slot: int) -> float:
        """The grid instant ``slot`` in s (whole periods first, so that a synchronous tick is exactly k * period)."""
        whole, part = divmod(int(slot), self.m)
        return whole * self.period + part * (self.period / self.m) if part else whole * self.period

    def next(self) -> tuple[int, np.ndarray]:
        """The next grid instant at which any cell ticks, and the cells that tick then (indices, ascending)."""
        s = int(self.slot.min())
        return s, np.flatnonzero(self.slot == s)

    def advance(self, rows: np.ndarray) -> None:
        """The cells ``rows`` just ticked: schedule their next tick (drift, then a fresh jitter draw)."""
        self.count[rows] += 1
        tau = self.count[rows] * (self.period * self.rate[rows])
        if self.p.jitter > 0:
            tau = tau + self.rng.uniform(0.0, self.p.jitter, len(rows))
        slot = np.ceil(tau * (self.m / self.period) - 1e-9).astype(np.int64)
        self.slot[rows] = np.maximum(slot, self.slot[rows] + 1)

    def nominal(self, i: int, k: int) -> float:
        """When cell ``i``'s ``k``-th tick is due before jitter and before it is put on the grid, s."""
        return k * (self.period * self.rate[i])

    def to_data(self) -> dict:
        """Its state as data: the random generator (``rng``), the ticks taken (``count``) and the next tick's grid
        instant (``slot``), per cell; the rates follow from the seed."""
        return {"rng": state_data.rng_to_data(self.rng), "count": self.count.copy(), "slot": self.slot.copy()}

    def load_data(self, d) -> None:
        """Go on from what :meth:`to_data` wrote (clocks of the same parameters); raises ValueError for other data."""
        d = state_data.fields(d, ("rng", "count", "slot"), "clock")
        count = state_data.array(d, "count", "i", (self.n,), "clock")
        slot = state_data.array(d, "slot", "i", (self.n,), "clock")
        if (count < 0).any() or (slot < 0).any():
            raise ValueError("clock: negative tick counts or instants")
        self.rng = state_data.rng_from_data(d["rng"], "clock.rng")
        self.count, self.slot = count.astype(np.int64), slot.astype(np.int64)


class Mailboxes:
    """One place per port of every cell holding the latest sentence that arrived there since the cell last read."""

    def __init__(self, mail: Mailbox):
        self.mail = mail

    def put(self, arrived: Mailbox) -> None:
        """Sentences that arrived (``arrived.present``) take their ports' places, replacing any not yet read."""
        hit = arrived.present
        if not hit.any():
            return
        self.mail.present |= hit
        for k, v in self.mail.values.items():
            np.copyto(v, arrived.values[k], where=hit)

    def read(self, rows: np.ndarray) -> None:
        """The cells ``rows`` have read their places: empty them (an empty place holds zeros, as a delivery's inbox
        does where nothing arrived)."""
        self.mail.present[rows] = False
        for v in self.mail.values.values():
            v[rows] = 0
