"""The sorter's due-tick calendar (:class:`DueCalendar`): the cells the time wakes at a tick
(:meth:`~virtual_vehicle.cells.sorting.Sorter.due`), found from the cells due then instead of by comparing every
cell's clocks every tick. Ticks are control ticks (the period's multiples), not seconds.

Why a calendar finds the same cells: a cell is due at tick T when a port it trusts turns stale then (it last heard
that port at ``T - trust - 1``), or when its heartbeat is at T or was at T - 1. A heartbeat's phase is fixed per cell
(its installation number modulo the heartbeat), so the cells of each phase are listed once. A port's last-heard tick
changes only where the cell is stepped (in place, by the compiled step or its clocks-only tick), and only to the tick
stepped: after each tick the cells stepped whose ports heard then are filed under the tick those turn stale, and at a
tick the cells filed under it are checked against their clocks now (a cell heard again since was filed again, later:
the check drops the old entry). Cells not stepped keep their clocks, so their earlier entries stand. The work a tick
is the cells stepped and the cells due, not the array.
"""

from __future__ import annotations

import numpy as np

from virtual_vehicle.cells.network.messages import rows_any
from virtual_vehicle.cells.sorting.rules import tick_of


class DueCalendar:
    """The cells :meth:`~virtual_vehicle.cells.sorting.Sorter.due` names at each tick, kept as they change.

    Args:
        n: cells.
        period: the control period, s (a time ``t`` is tick ``t / period``).
        trust: ticks a neighbour's last sentence is trusted after it arrived (a port heard at tick h turns stale at
            ``h + trust + 1``).
        heartbeat: ticks between two heartbeats of a cell (1: none to wake a cell for).
        number: (n,) the cells' installation numbers, which stagger their heartbeats.
        ask_after: a port last heard more than this many ticks ago and still trusted makes its cell ask (due every
            tick); None: cells never ask (the wire's partial sentences).

    Use (``state``: the sorter's state dict, of which only ``heard_at`` is read): :meth:`restart` from the whole
    state (every cell filed), then each tick :meth:`due` before stepping and :meth:`stepped` with the cells stepped,
    after. A step whose cells were not filed (stepped without telling the calendar) needs a :meth:`restart`.
    """

    def __init__(self, n: int, period: float, trust: int, heartbeat: int, number: np.ndarray,
                 ask_after: int | None = None):
        self.n = int(n)
        self.ask_after = None if ask_after is None or ask_after >= trust else int(ask_after)
        self._ask_buckets: dict[int, list[np.ndarray]] = {}
        """Tick -> arrays of cells one of whose ports may enter the asking window then."""
        self._askers = np.zeros(0, dtype=np.int64)
        """Cells asking at the last tick checked (or filed to start then)."""
        self.period = float(period)
        self.trust = int(trust)
        self.heartbeat = int(heartbeat)
        self._buckets: dict[int, list[np.ndarray]] = {}
        """Tick -> arrays of cells that may turn a port stale then (duplicates and stale entries allowed)."""
        self.tick: int | None = None
        """The last tick filed (None: not started)."""
        self._phases = None
        if self.heartbeat > 1:  # the cells of each heartbeat phase, listed once: (tick + number) % heartbeat == 0
            phase = np.broadcast_to(np.asarray(number, dtype=np.int64), (self.n,)) % self.heartbeat
            order = np.argsort(phase, kind="stable")
            self._phases = (order, np.searchsorted(phase[order], np.arange(self.heartbeat + 1)))

    def restart(self, t: float, state: dict) -> None:
        """Forget what was filed and file every cell from its clocks in ``state`` under the ticks after the tick at
        ``t`` (s) at which one of its ports turns stale."""
        self._buckets.clear()
        self._ask_buckets.clear()
        tick = self.tick = tick_of(t, self.period)
        if self.ask_after is not None:  # each port filed under the tick its asking window opens (passed: at once)
            opens = np.maximum(state["heard_at"] + (self.ask_after + 1), tick + 1)
            trusted = state["heard_at"] + self.trust > tick
            cells = np.broadcast_to(np.arange(self.n)[:, None], opens.shape)[trusted]
            opens = opens[trusted]
            for t_open in np.unique(opens).tolist():
                self._ask_buckets.setdefault(t_open, []).append(cells[opens == t_open])
            self._askers = np.zeros(0, dtype=np.int64)
        at = state["heard_at"] + (self.trust + 1)  # (n, P) the tick each port turns stale
        later = at > tick
        cells = np.broadcast_to(np.arange(self.n)[:, None], at.shape)[later]
        at = at[later]
        for t_due in np.unique(at).tolist():
            self._buckets.setdefault(t_due, []).append(cells[at == t_due])

    def stepped(self, t: float, state: dict, rows: np.ndarray) -> None:
        """File the cells ``rows``, stepped at the tick at ``t`` (s), whose ports heard then under the tick those
        turn stale. A step sets a port's last-heard tick only to its own tick, so the ports it did not set were
        filed when they were set (or at :meth:`restart`)."""
        tick = self.tick = tick_of(t, self.period)
        if len(rows):
            heard = rows[rows_any(state["heard_at"][rows] == tick)]
            if len(heard):
                self._buckets.setdefault(tick + self.trust + 1, []).append(heard)
                if self.ask_after is not None:
                    self._ask_buckets.setdefault(tick + self.ask_after + 1, []).append(heard)

    def due(self, t: float, state: dict) -> np.ndarray:
        """(n,) the cells due at the tick at ``t`` (s; the next tick after the last filed): equal to
        :meth:`~virtual_vehicle.cells.sorting.Sorter.due` on the same state."""
        tick = tick_of(t, self.period)
        heard_at = state["heard_at"]
        for t in [t for t in self._buckets if t < tick]:  # passed without a step (none filed since): never due again
            del self._buckets[t]
        woken = np.zeros(self.n, dtype=bool)
        filed = self._buckets.pop(tick, None)
        if filed:
            cells = filed[0] if len(filed) == 1 else np.concatenate(filed)
            woken[cells] = rows_any(heard_at[cells] == tick - self.trust - 1)
        if self.ask_after is not None:  # askers: those of last tick and those whose window opens now (or opened
            # at a tick passed without a call), each checked against its clocks
            opened = [self._askers]
            for t in [t for t in self._ask_buckets if t <= tick]:
                opened.extend(self._ask_buckets.pop(t))
            cells = np.unique(np.concatenate(opened)) if len(opened) > 1 else self._askers
            ago = tick - heard_at[cells]
            cells = cells[rows_any((ago > self.ask_after) & (ago <= self.trust))]
            woken[cells] = True
            self._askers = cells
        if self._phases is not None:
            order, bounds = self._phases
            for g in {(-tick) % self.heartbeat, (1 - tick) % self.heartbeat}:  # its heartbeat now, or last tick
                woken[order[bounds[g]:bounds[g + 1]]] = True
        return woken
