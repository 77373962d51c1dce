"""The clocked run (:class:`ClockedRun`): a networked run whose cells tick on their own clocks (``[control.clock]``
drift and jitter); the plant goes on only to the instants where the wheels held change, and the cells that tick in
between read the parcels where a look ahead under those wheels puts them.

Units: SI (s, m/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from virtual_vehicle.cells.network.clocks import CellClocks, Mailboxes
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import CellInputs, step_group
from virtual_vehicle.config.scenario import Setup
from virtual_vehicle.model.state_data import array, fields, number
from virtual_vehicle.run.network import _FAULTS, NetworkRun, _labels
from virtual_vehicle.run.results import RunResult

class ClockedRun(NetworkRun):
    """A networked run whose cells tick on their own clocks (:mod:`virtual_vehicle.cells.network.clocks`).

    A step goes from one instant at which some cells tick to the next: the faults, cell changes and arrivals due
    take effect and every cell's sensors are read (the plant's state then), the cells that tick read their
    mailboxes and step their program, their wheel commands take effect and their sentences go out; the other
    cells' wheels hold what they last asked for. Ideal rounds deliver by time: a sentence is in the receiver's
    mailbox from the next instant on; the wire model times it. With no drift and no jitter every cell ticks at
    every k * period and this is the synchronous run (:class:`NetworkRun`, stepping every cell) to the last bit.
    The network record keeps its traffic per period. The program's ``t`` is the instant on the run's time line (the
    sorter counts its ticks from it: a cell's tick number is that instant in periods, rounded)."""

    KIND = "clocked"
    STATE = (*NetworkRun.STATE, "clock", "held", "ticked", "plant_t", "ahead_to")
    """:attr:`NetworkRun.STATE` (its ``inbox`` being the mailboxes, ``k`` the steps taken), the clocks
    (:meth:`CellClocks.to_data`), the (n, 2) wheel speeds each cell last asked for (m/s) and, when the cell log is
    kept, which cells ticked when (``ticked``: ``t`` s and ``cell``, one entry a cell's tick; None otherwise) and the
    time the plant stands at (``plant_t``, s: the parcels' states, tracks and plant state are of then) and how far it
    looked ahead from there (``ahead_to``, s; None for no look ahead: a resumed run looks as far again)."""

    def __init__(self, setup: Setup):
        super().__init__(setup)
        ctl = setup.control
        n, P = ctl.topology.n, ctl.topology.ports
        self.stepper = None  # the cells that tick are the ones stepped
        self.clocks = CellClocks(n, self.period, ctl.clock)
        self.mail = Mailboxes(self.inbox)
        self.held = np.zeros((n, 2))
        self.outbox = Mailbox.empty(ctl.program.schema, n, P)
        self.after: int | None = None  # the instant after this step's, once its cells have ticked
        self.ticked: dict | None = {"t": [], "cell": []} if self.record else None
        # The plant goes on only to instants where the wheels held change (one call between two such instants);
        # the cells that tick in between read the parcels where a look ahead under the wheels held puts them.
        # Motor wheels change while their commands hold, and a cell log keeps a row an instant: those go instant by
        # instant, and so does the synchronous case (one instant a period: the synchronous run to the last bit).
        self.lazy = self.drives is None and not self.record and not ctl.clock.synchronous
        self.plant_t = 0.0  # s, where the plant stands (the parcels' ys, tracks and plant state are of then)
        self.holding: tuple[np.ndarray, np.ndarray] | None = None  # the wheel speeds held since and their velocities
        self.ahead: _Ahead | None = None  # the look ahead from plant_t, when one was made
        self.ahead_to: float | None = None  # how far the next look ahead goes, when that is known (a resumed run)
        self.now_ys: list[np.ndarray] = self.ys  # the parcels' states at this step's instant

    def most_steps(self) -> int:
        """Steps are instants at which some cell ticks: at most every grid instant of the run."""
        return self.ticks * self.clocks.m + 1

    @property
    def done(self) -> bool:
        """True once the next instant any cell ticks is at or past the end."""
        return self.clocks.time_of(int(self.clocks.slot.min())) >= self.end - 1e-9 * self.period

    def span(self) -> tuple[float, float]:
        """(start, end) of this step, s: the instant the cells tick and the next one any cell ticks."""
        now = int(self.clocks.slot.min()) if self.after is None else self.now
        t0 = self.clocks.time_of(now)
        whole = self.after is None or self.after - now == self.clocks.m  # a period on: as the synchronous run
        t1 = t0 + self.period if whole else self.clocks.time_of(self.after)
        return t0, min(self.end, t1)

    def hold_time(self) -> float:
        """s to the next instant (the period exactly when that is a whole period on)."""
        if self.after - self.now == self.clocks.m:
            return self.period
        t0, t1 = self.span()
        return t1 - t0

    def step(self, every, progress) -> bool:
        """One instant's ticks; True when a checkpoint is due (a multiple of ``every`` s was passed)."""
        t_before = self.span()[0]
        self.tick()
        t_after = self.span()[0]
        if progress is not None:
            progress(min(1.0, t_after / self.end) if self.end > 0 else 1.0)
        return every is not None and math.floor(t_after / every + 1e-9) > math.floor(t_before / every + 1e-9)

    def tick(self) -> None:
        """The cells whose clocks tick at the next instant read and decide; the plant goes on to the instant after
        (or, :attr:`lazy`, to where the wheels held next change)."""
        self.now = int(self.clocks.slot.min())
        if not self.lazy:
            self.now_ys = self.ys
            sensors = self.begin()
            stats = self._decide(sensors)
            self.finish(self.held, sensors, stats.sent, stats.received)
            self.after = None
            return
        t0 = self.clocks.time_of(self.now)
        if self._events_due(t0):  # faults, cell changes and arrivals act on the parcels where they are now
            self._plant_to(t0)
        self._inject(t0)
        self._reconfigure(t0)
        self._admit(t0)
        self.now_ys = ys = self._states_at(t0)
        rows = np.flatnonzero(self.clocks.slot == self.now)
        sensors = self._sense(rows, ys)
        self._decide(sensors)
        _, wheels, velocities = self.wheels_held(self.held, self.period)
        if self.holding is None or not np.array_equal(wheels, self.holding[0]):
            self._plant_to(t0)  # the wheels held so far hold until now
            self.holding = (wheels, velocities)
        self.k += 1
        self.after = None
        if self.done:
            self._plant_to(self.end)
        self.now_ys = self.ys

    def _sense(self, rows: np.ndarray, ys: list[np.ndarray]) -> np.ndarray:
        """(n, S) readings of the cells ``rows`` with the parcels at states ``ys`` (the others read nothing: they
        do not tick now)."""
        setup, on = self.setup, self.on
        sensors = self.sensors.read([setup.specs[i] for i in on], [ys[i] for i in on], self.sensor_rng, rows=rows)
        if self.present is not None:
            sensors[~self.present] = 0  # a cell taken out senses nothing
        return sensors

    def _events_due(self, t: float) -> bool:
        """Whether a fault event, a cell change or a parcel's arrival is due by ``t`` (s)."""
        setup, tol = self.setup, 1e-9 * max(1.0, t)
        return ((self.next_fault < len(setup.fault_events) and setup.fault_events[self.next_fault][0] <= t + tol)
                or (self.next_change < len(setup.cell_changes) and setup.cell_changes[self.next_change][0] <= t + tol)
                or bool(self.queue and self.arrive[self.queue[0]] <= t + 1e-12))

    def _plant_to(self, t: float) -> None:
        """The plant carries the parcels from :attr:`plant_t` to ``t`` (s) under the wheels held, in one call (the
        look ahead taken where it ends there, taken back where it went further)."""
        if t <= self.plant_t:
            return
        self._look_again()
        ahead, self.ahead = self.ahead, None
        if ahead is not None and ahead.end <= t:
            self.ys, self.active = ahead.ys, ahead.active
            self.take_in(ahead.trajectories, ahead.quiet, ahead.window, self.holding[1])
            self.plant_t = ahead.end
        elif ahead is not None:
            self.plant.restore(ahead.plant)  # it went past t: back to plant_t
        if t > self.plant_t:
            self.carry(self.plant_t, t, self.holding[1], t - self.plant_t)
            self.plant_t = t

    def _states_at(self, t: float) -> list[np.ndarray]:
        """The parcels' states at ``t`` (s; the plant's own where it stands there, else from a look ahead under the
        wheels held, to a period past :attr:`plant_t` or ``t`` if later, made once and kept)."""
        if t <= self.plant_t:
            return self.ys
        self._look_again()
        if self.ahead is not None and self.ahead.end < t:
            self._plant_to(self.ahead.end)  # no wheel changed to its end: it stands
        if self.ahead is None:
            self._look_ahead(max(t, min(self.plant_t + self.period, self.end)))
        found = self.ahead.states_at(t, self.on, self.ys)
        if found is None:  # a parcel's piece does not reach t (it tipped): the plant goes there itself
            self._plant_to(t)
            return self.ys
        return found

    def _look_again(self) -> None:
        """A run resumed from a checkpoint taken during a look ahead (:attr:`ahead_to` known, none made yet) makes
        that look ahead again, from the same state to the same end, before the plant goes anywhere: the plant's
        calls then split where the uninterrupted run's did (a call cut elsewhere differs in the last bits)."""
        if self.ahead is None and self.ahead_to is not None:
            end, self.ahead_to = self.ahead_to, None
            self._look_ahead(end)

    def _look_ahead(self, end: float) -> None:
        """Look ahead from :attr:`plant_t` to ``end`` (s) under the wheels held, sampled at every grid instant on
        the way and at the output grid; the plant's state before it is kept to go back to."""
        t0 = self.plant_t
        m, c = self.clocks.m, self.clocks
        first, last = int(math.floor(t0 * m / self.period)), int(math.ceil(end * m / self.period))
        instants = [c.time_of(s) for s in range(first, last + 1)]
        window = self.window(t0, end)
        samples = np.union1d(window, [x for x in instants if t0 < x <= end])
        state = self.plant.state()
        ys, active = [y.copy() for y in self.ys], list(self.active)
        trajectories, quiet = self.plant.advance_blocks(ys, active, self.holding[1], t0, end, end - t0,
                                                        sample_times=samples)
        self.ahead = _Ahead(end, ys, active, trajectories, quiet, window, state)

    def _decide(self, sensors: np.ndarray):
        """The cells that tick now step on their sensors, mailboxes and labels and send; the others hold. Returns
        the traffic statistics of the step (also added to the network record, in its period)."""
        setup, ctl = self.setup, self.setup.control
        clocks, topo = self.clocks, self.topology
        rows = np.flatnonzero(clocks.slot == self.now)
        t0, _ = self.span()
        ys, on = self.now_ys, self.on
        labelled = any(self.destinations[i] is not None for i in on)
        labels = _labels(setup, [ys[i] for i in on], [setup.specs[i] for i in on],
                         [self.destinations[i] for i in on]) if labelled else None
        inputs = CellInputs(t0, sensors, self.inbox, topo.connected, self._program_config(), labels)
        n = topo.n
        if len(rows) == n:  # every cell ticks: one step of all (as the synchronous run)
            self.state, outbox, wheels = ctl.program.step(self.state, inputs)
            self.held = np.array(wheels, dtype=float)
            send = outbox
        else:
            self.state = step_group(ctl.program, self.state, inputs, rows, self.outbox, self.held)
            ticks = np.zeros(n, dtype=bool)
            ticks[rows] = True
            send = Mailbox(self.outbox.schema, self.outbox.present & ticks[:, None], self.outbox.values)
        self.mail.read(rows)
        if self.ticked is not None:
            self.ticked["t"].append(np.full(len(rows), t0))
            self.ticked["cell"].append(rows.copy())
        clocks.advance(rows)
        self.after = int(clocks.slot.min())
        gap = self.after - self.now
        dt = self.period if gap == clocks.m else clocks.time_of(self.after) - t0
        arrived, stats = self.delivery.exchange(send, t0, dt)
        self.mail.put(arrived)
        b = min(int(math.floor(t0 / self.period + 1e-9)), self.ticks - 1)  # the period this step is in
        before = int(self.per_tick["received"][b])
        for key in ("sent", "received", "bytes_sent", "bytes_received"):
            self.per_tick[key][b] += int(getattr(stats, key).sum())
            self.per_cell[f"cell_{key}"] += getattr(stats, key)
        for key in _FAULTS:
            self.per_tick[key][b] += getattr(stats, key)
        lat = stats.latencies
        if len(lat):
            old_mean = self.per_tick["latency_mean"][b]
            self.per_tick["latency_mean"][b] = (lat.mean() if np.isnan(old_mean) else
                                                (old_mean * before + lat.sum()) / (before + len(lat)))
            self.per_tick["latency_max"][b] = np.fmax(self.per_tick["latency_max"][b], lat.max())
            self.latency.add(lat)
        return stats

    def tick_times(self, cell: int) -> np.ndarray:
        """The instants (s) cell ``cell`` ticked at so far, from the log kept with ``[sensors] record = true``."""
        if self.ticked is None:
            raise ValueError("the ticks are logged only when the scenario records ([sensors] record = true)")
        t = np.concatenate([np.zeros(0), *self.ticked["t"]])
        c = np.concatenate([np.zeros(0, dtype=np.int64), *self.ticked["cell"]])
        return t[c == cell]

    def _cells_added(self, added: np.ndarray) -> None:
        """The cells ``added`` start their program afresh, with empty mailboxes and still wheels."""
        super()._cells_added(added)
        rows = np.flatnonzero(added)
        self.mail.read(rows)
        self.held[rows] = 0.0

    def _state(self) -> dict:
        ticked = None
        if self.ticked is not None:
            ticked = {"t": np.concatenate([np.zeros(0), *self.ticked["t"]]),
                      "cell": np.concatenate([np.zeros(0, dtype=np.int64), *self.ticked["cell"]])}
        d = {**super()._state(), "clock": self.clocks.to_data(), "held": self.held.copy(), "ticked": ticked,
             "plant_t": float(self.plant_t),
             "ahead_to": float(self.ahead.end) if self.ahead is not None else self.ahead_to}  # one not yet made again
        if self.ahead is not None:
            d["plant"] = self.ahead.plant  # the plant's state where it stands, not where it looked ahead to
        return d

    def _restore(self, position: dict, state, arrays: list) -> None:
        super()._restore(position, state, arrays)
        s = self._read_state(state, arrays)
        n = self.topology.n
        self.clocks.load_data(s["clock"])
        self.held = array(s, "held", "f", (n, 2), "state").astype(float)
        self.mail = Mailboxes(self.inbox)
        self.after = None
        self.plant_t = number(s, "plant_t", "state")
        self.ahead = None
        self.ahead_to = None if s["ahead_to"] is None else number(s, "ahead_to", "state")
        if self.ahead_to is not None and not self.plant_t < self.ahead_to <= self.end:
            raise ValueError(f"state.ahead_to: {self.ahead_to} s is not between plant_t and the run's end")
        self.holding = None
        if self.k:  # the wheels held since plant_t: what the cells last asked for, as the wheels take it
            _, wheels, velocities = self.wheels_held(self.held, self.period)
            self.holding = (wheels, velocities)
        self.now_ys = self.ys
        if (s["ticked"] is None) != (self.ticked is None):
            raise ValueError("state.ticked: the tick log is kept exactly when the cell log is")
        if s["ticked"] is not None:
            d = fields(s["ticked"], ("t", "cell"), "state.ticked")
            t = array(d, "t", "f", (None,), "state.ticked")
            self.ticked = {"t": [t], "cell": [array(d, "cell", "i", (len(t),), "state.ticked").astype(np.int64)]}

    def result(self) -> RunResult:
        """:meth:`NetworkRun.result`, with the clocks in the summary's ``network.clocks``."""
        res = super().result()
        c, p = self.clocks, self.setup.control.clock
        res.stats["network"]["clocks"] = {
            "drift": p.drift, "jitter_s": p.jitter, "seed": p.seed, "slots_per_period": p.slots,
            "rate_min": float(c.rate.min()), "rate_max": float(c.rate.max()), "instants": int(self.k),
            "ticks_min": int(c.count.min()), "ticks_max": int(c.count.max()),
            "cells_a_instant": float(c.count.sum() / max(self.k, 1))}
        return res


@dataclass
class _Ahead:
    """A look ahead of the plant from where it stands to ``end`` (s) under the wheels held: the parcels' states and
    flags there, what the plant returned (sampled at every grid instant on the way), the output ``window`` of it and
    the plant's ``plant`` state before it (to go back to)."""

    end: float
    ys: list
    active: list
    trajectories: list
    quiet: list
    window: np.ndarray
    plant: dict

    def states_at(self, t: float, on: list[int], ys: list[np.ndarray]) -> list[np.ndarray] | None:
        """The states at ``t`` (s, a sample of the look ahead) of the parcels ``on`` (``ys`` for the others), or
        None when one of them has no sample at ``t``."""
        out = list(ys)
        by_quiet = {i: (steps, k) for i, steps, k in self.quiet}
        for i in on:
            if i in by_quiet:
                steps, k = by_quiet[i]
                times, states, row = steps.times, steps.states, steps.rows[k]
            elif self.trajectories[i] is not None:
                times, states, row = self.trajectories[i].times, self.trajectories[i].states, None
            else:
                return None
            j = int(np.searchsorted(times, t))
            if j >= len(times) or times[j] != t:
                return None
            out[i] = states[j] if row is None else states[row, j]
        return out
