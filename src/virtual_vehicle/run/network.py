"""The networked run: a run that goes one control tick at a time, whoever decides the wheels (:class:`TickedRun`,
shared with the environments of :mod:`virtual_vehicle.ui.envs`), and the run whose cell programs and network decide
at every tick (:class:`NetworkRun`), with what the tick needs (the wheels' loads, the parcels' labels).

Units: SI (s, m, m/s, N).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import shapely

from virtual_vehicle.cells.hardware import WheelDrives
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.programs import CellInputs, ChangedCells, tree_map
from virtual_vehicle.cells.sorting import encode_goal
from virtual_vehicle.config.scenario import Setup
from virtual_vehicle.engine.dynamics import Trajectory, sample_grid
from virtual_vehicle.engine.plant import on_grid
from virtual_vehicle.model.parcel import covered_pairs
from virtual_vehicle.model.state_data import array, fields, integer, number, rng_from_data, rng_to_data
from virtual_vehicle.run.jobs import _Job
from virtual_vehicle.run.results import (CellLog, LatencyStats, NetworkRecord, ParcelResult, RunResult, _sliding,
                                         plant_totals)
from virtual_vehicle.run.tracks import ParcelTrack, _stack

_FAULTS = ("lost", "corrupted", "undetected", "dropped", "unaddressed")

_CELL_LOG = ("t", "readings", "wheels", "commands", "sent", "received")
"""The columns of a ticked run's cell log, as :class:`CellLog` names them."""


def wheel_loads(setup: Setup, models, states, active, speeds: np.ndarray) -> np.ndarray:
    """(n, 2) friction force (N) each wheel exerts on the parcels above it along its drive direction, whose reaction
    loads the wheel: Coulomb mu N in the direction of spin (paper 4.3), viscous mu N times the slip (eq. 30),
    stick-slip mu N against the slip (zero while a wheel is stuck). ``speeds`` are the wheels' surface speeds."""
    cells = setup.cells
    law = setup.law
    load = np.zeros((cells.n, 2))
    for model, y, on in zip(models, states, active):
        if not on:
            continue
        piece = model.piece_at(y)
        ids, N = piece.support, piece.normal_forces(y)
        r = cells.positions[ids] - y[:2]
        v = y[3:5] + y[5] * np.column_stack([-r[:, 1], r[:, 0]])  # parcel velocity over each cell
        for k in range(2):
            u = cells.drive_directions[ids, k]
            w = speeds[ids, k]
            slip = w - np.einsum("ij,ij->i", v, u)
            load[ids, k] += model.spec.mu * N * law.wheel_loads(w, slip)
    return load


def _check_like(fresh, loaded, where: str = "state") -> None:
    """Raise ValueError where ``loaded`` (a run's state read from a checkpoint) is not shaped as ``fresh`` (the same
    run's state at its start): every array the start has (by key, attribute or position in lists of equal length)
    must be there with the same dtype and shape, every object of the same class, every number a number of its
    kind."""
    import numbers

    if isinstance(fresh, (bool, np.bool_)):
        if not isinstance(loaded, (bool, np.bool_)):
            raise ValueError(f"{where} is not a truth value")
    elif isinstance(fresh, numbers.Integral):
        if not isinstance(loaded, numbers.Integral) or isinstance(loaded, (bool, np.bool_)):
            raise ValueError(f"{where} is not an integer")
    elif isinstance(fresh, numbers.Real):
        if not isinstance(loaded, numbers.Real) or isinstance(loaded, (bool, np.bool_)):
            raise ValueError(f"{where} is not a number")
    elif isinstance(fresh, np.ndarray):
        if not (isinstance(loaded, np.ndarray) and loaded.dtype == fresh.dtype and loaded.shape == fresh.shape):
            got = f"{loaded.dtype} {loaded.shape}" if isinstance(loaded, np.ndarray) else type(loaded).__name__
            raise ValueError(f"{where} is {got}, not {fresh.dtype} {fresh.shape}")
    elif isinstance(fresh, dict):
        if not isinstance(loaded, dict) or not fresh.keys() <= loaded.keys():
            raise ValueError(f"{where} lacks {sorted(map(str, fresh))}")
        for k, v in fresh.items():
            _check_like(v, loaded[k], f"{where}[{k!r}]")
    elif isinstance(fresh, (list, tuple)):
        if type(loaded) is not type(fresh):
            raise ValueError(f"{where} is not a {type(fresh).__name__}")
        if len(fresh) == len(loaded):
            for k, (a, b) in enumerate(zip(fresh, loaded)):
                _check_like(a, b, f"{where}[{k}]")


def _reset_rows(state, fresh, rows: np.ndarray):
    """``state`` (a program's per-cell arrays, nested in dicts, tuples or dataclasses) with the rows ``rows`` of every
    per-cell array taken from ``fresh`` (the program's initial state)."""

    def reset(a, b):
        if isinstance(a, np.ndarray) and a.ndim >= 1 and a.shape[0] == len(rows):
            out = a.copy()
            out[rows] = b[rows]
            return out
        return a

    return tree_map(reset, state, fresh)


class TickedRun:
    """A run that goes one control tick at a time, whoever decides the wheels: the parcels (arriving, carried,
    leaving), the plant, the wheels' motors, the faults and the cells installed now, and what is recorded.

    A tick is :meth:`begin` (the fault events and cell changes due take effect, the parcels due come on the array,
    the cells read their sensors), a decision (the wheel speeds to hold: the cell programs and their network in
    :class:`NetworkRun`, an agent in :mod:`virtual_vehicle.ui.envs`) and :meth:`finish` (belts, motors, faults, the
    plant, the Coulomb check, the records). Both share this one code, so that an environment fed a run's commands
    moves the parcels as the run does, to the last bit.

    Args:
        setup: the built scenario.
        period: s between ticks.
        end: s, where the last tick ends (default the scenario's duration).
        grid: the output sample times (s) the parcels' tracks keep (default every tick's end).
        topology: the cells' links at the start (default the layout's, less the scenario's dead cells and links).
        record: keep a :class:`CellLog` row a tick (default the scenario's ``[sensors] record``).
        states: the parcels' starting states (default the scenario's).
        sensor_rng: draws the sensors' noise (default seeded with the scenario's sensor seed).
    """

    def __init__(self, setup: Setup, period: float, *, end: float | None = None, grid: np.ndarray | None = None,
                 topology=None, record: bool | None = None, states=None, sensor_rng: np.random.Generator | None = None):
        sc = setup.scenario
        self.setup = setup
        self.period = period
        self.end = sc.duration if end is None else end
        self.grid = grid
        self.record = sc.sensors.record if record is None else record
        self.k = 0
        self.sensor_rng = np.random.default_rng(setup.sensors.seed) if sensor_rng is None else sensor_rng
        self.drives = WheelDrives(setup.cells.n, sc.wheels.motor()) if sc.wheels.model == "motor" else None
        self.ys = [y.copy() for y in (setup.states if states is None else states)]
        self.saturate = sc.arrivals == "saturate"  # every parcel queued at its place from the start
        self.arrive = [0.0 if self.saturate else p.t_start for p in sc.parcels]
        self.active = [t == 0 and not self.saturate for t in self.arrive]
        self.on = [i for i, a in enumerate(self.active) if a]  # the active parcels, in order
        self.queue = sorted((i for i, t in enumerate(self.arrive) if t > 0 or self.saturate),
                            key=lambda i: (self.arrive[i], i))
        self.entered = [None if self.saturate else 0.0 if t == 0 else None for t in self.arrive]
        self.plant = setup.plant()
        self.tracks = [ParcelTrack() for _ in self.ys]
        self.cell_log: list = []
        self.faults = setup.faults  # these and the topology change when faults are injected during the run
        self.sensors = setup.sensors
        self.next_fault = 0
        self.injected: list[dict] = []
        self.present = setup.present  # cells installed now (None: all, always)
        self.topology = self._links() if topology is None else topology
        self.next_change = 0
        self.reconfigured: list[dict] = []
        # the paper's Coulomb assumption, checked at every output sample against that tick's wheels (4.3)
        self.sliding: list | None = [None] * len(self.ys) if setup.law.assumes_sliding else None
        if self.present is not None and not self.present.all():
            self._rewire()

    TICKED_STATE = ("k", "ys", "active", "on", "queue", "entered", "sliding", "injected", "reconfigured",
                    "sensor_rng", "drives", "tracks", "plant", "cell_log")
    """The fields that are a ticked run's state (:meth:`ticked_state`)."""

    def ticked_state(self) -> dict:
        """The ticked run's state as data (arrays and plain values), by field: the ticks done ``k``, every parcel's
        state ``ys`` (N, 6), which are on the array (``active``, ``on`` in order), the ``queue`` of those waiting and
        when each came on (``entered`` (N,) s, NaN before), the Coulomb check so far (``sliding``: which parcels
        broke it, first time s and worst slip m/s; None when not checked), the fault events and cell changes
        applied (``injected``, ``reconfigured``: their summaries), the sensors' random generator, the motors
        (:meth:`WheelDrives.to_data`, None without), the parcels' tracks (:meth:`ParcelTrack.to_data`), the plant's state
        and the cell log as columns (None when empty)."""
        N = len(self.ys)
        sliding = None
        if self.sliding is not None:
            sliding = {"found": np.array([x is not None for x in self.sliding], dtype=bool),
                       "at": np.array([x if x is not None else (np.nan, np.nan) for x in self.sliding],
                                      dtype=np.float64).reshape(N, 2)}
        log = None
        if self.cell_log:
            log = dict(zip(_CELL_LOG, (np.asarray(column) for column in zip(*self.cell_log))))  # an array a column
        return {"k": int(self.k), "ys": _stack(self.ys), "active": np.array(self.active, dtype=bool),
                "on": np.array(self.on, dtype=np.int64), "queue": np.array(self.queue, dtype=np.int64),
                "entered": np.array([np.nan if t is None else t for t in self.entered], dtype=np.float64),
                "sliding": sliding, "injected": self.injected, "reconfigured": self.reconfigured,
                "sensor_rng": rng_to_data(self.sensor_rng),
                "drives": None if self.drives is None else self.drives.to_data(),
                "tracks": [track.to_data() for track in self.tracks], "plant": self.plant.state(), "cell_log": log}

    def load_ticked_state(self, s: dict) -> None:
        """Take up what :meth:`ticked_state` wrote (of a run of the same setup, made afresh); raises ValueError for
        data that does not fit it."""
        where = "state"
        N, n = len(self.setup.specs), self.setup.cells.n
        k = integer(s, "k", where)
        ys = array(s, "ys", "f", (N, 6), where)
        active = array(s, "active", "b", (N,), where).tolist()
        on, queue = (array(s, key, "i", (None,), where).tolist() for key in ("on", "queue"))
        if not (set(on) <= set(range(N)) and set(queue) <= set(range(N)) and on == sorted(set(on))):
            raise ValueError(f"{where}: parcels on the array or waiting that are not the scenario's")
        entered = array(s, "entered", "f", (N,), where)
        if (s["sliding"] is None) != (self.sliding is None):
            raise ValueError(f"{where}.sliding: the Coulomb check is {'not ' if self.sliding is None else ''}made")
        sliding = None
        if s["sliding"] is not None:
            d = fields(s["sliding"], ("found", "at"), f"{where}.sliding")
            found = array(d, "found", "b", (N,), f"{where}.sliding").tolist()
            at = array(d, "at", "f", (N, 2), f"{where}.sliding").tolist()
            sliding = [tuple(x) if f else None for f, x in zip(found, at)]
        for key in ("injected", "reconfigured"):
            if type(s[key]) is not list or not all(type(x) is dict for x in s[key]):
                raise ValueError(f"{where}.{key}: not a list of summaries")
        if (s["drives"] is None) != (self.drives is None):
            raise ValueError(f"{where}.drives: not the scenario's wheels")
        drives = None if self.drives is None else WheelDrives.from_data(s["drives"], self.drives.p, f"{where}.drives")
        if drives is not None and drives.speed.shape != (n, 2):
            raise ValueError(f"{where}.drives: {len(drives.speed)} cells, not {n}")
        tracks = s["tracks"]
        if type(tracks) is not list or len(tracks) != N:
            raise ValueError(f"{where}.tracks: not one track per parcel")
        log = []
        if s["cell_log"] is not None:
            d = fields(s["cell_log"], _CELL_LOG, f"{where}.cell_log")
            T = len(array(d, "t", "f", (None,), f"{where}.cell_log"))
            columns = [array(d, key, kind, shape, f"{where}.cell_log") for key, kind, shape in (
                ("t", "f", (T,)), ("readings", "b", (T, n, None)), ("wheels", "f", (T, n, 2)),
                ("commands", "f", (T, n, 2)), ("sent", "i", (T, n)), ("received", "i", (T, n)))]
            log = list(zip(*columns))
        self.tracks = [ParcelTrack.from_data(d, f"{where}.tracks[{i}]") for i, d in enumerate(tracks)]
        self.sensor_rng = rng_from_data(s["sensor_rng"], f"{where}.sensor_rng")
        self.plant.restore(s["plant"])
        self.k, self.ys, self.active, self.on, self.queue = k, [row.copy() for row in ys], active, on, queue
        self.entered = [None if np.isnan(t) else t for t in entered.tolist()]
        self.sliding, self.drives, self.cell_log = sliding, drives, log
        self.injected, self.reconfigured = s["injected"], s["reconfigured"]

    def span(self) -> tuple[float, float]:
        """(start, end) of the next tick, s."""
        t0 = self.k * self.period
        return t0, min(self.end, t0 + self.period)

    def hold_time(self) -> float:
        """s the wheels hold the next tick's commands, as the motors and the plant are told (the period)."""
        return self.period

    def begin(self) -> np.ndarray:
        """The first half of the next tick, up to the decision: the fault events and cell changes due by its start
        take effect, the parcels due come on the array, and the cells read their sensors. Returns the (n, S)
        readings (a cell taken out reads nothing)."""
        setup = self.setup
        t0, _ = self.span()
        self._inject(t0)
        self._reconfigure(t0)
        ys = self.ys
        self._admit(t0)
        on = self.on
        sensors = self.sensors.read([setup.specs[i] for i in on], [ys[i] for i in on], self.sensor_rng)
        if self.present is not None:
            sensors[~self.present] = 0  # a cell taken out senses nothing
        return sensors

    def finish(self, command: np.ndarray, sensors: np.ndarray, sent: np.ndarray, received: np.ndarray) -> np.ndarray:
        """The second half of the tick :meth:`begin` started: the cells ask for ``command`` ((n, 2) wheel surface
        speeds along their drive directions, m/s); a dead cell does not drive, plain belts run at their own speed,
        motor wheels follow through their dynamics, stuck wheels stay still, and the plant carries every parcel
        over the tick under the wheels held (zero-order hold). ``sensors`` (the readings :meth:`begin` returned) and
        ``sent`` / ``received`` ((n,) sentences) go into the cell log when it is kept. Returns the (n, 2) wheel
        speeds the tick held, m/s (a motor wheel's mean over it)."""
        period = self.hold_time()
        t0, t1 = self.span()
        command, wheels, velocities = self.wheels_held(command, period)
        if self.record:
            self.cell_log.append((t0, sensors.astype(bool), np.array(wheels, dtype=float), command.copy(),
                                  np.array(sent), np.array(received)))
        if t1 > t0:
            self.carry(t0, t1, velocities, period)
        self.k += 1
        return wheels

    def wheels_held(self, command: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the cells' ``command`` ((n, 2) m/s) holds for ``period`` s: the commands as the wheels take them
        (dead cells still, plain belts at their own speed), the wheel speeds (motors followed, stuck wheels still)
        and the contact-layer velocities the plant is driven by (m/s)."""
        setup, cells = self.setup, self.setup.cells
        ys, active = self.ys, self.active
        command = np.where(self.topology.alive[:, None], np.asarray(command, dtype=float), 0.0)  # dead cells: still
        command = cells.belt_commands(command)  # plain belts run at their own speed
        if self.drives is None:
            wheels = command
        else:
            load = wheel_loads(setup, self.plant.base, ys, active, self.drives.speed)
            wheels = self.drives.step(command, load, period)
        if self.faults is not None:
            wheels = self.faults.hold(wheels)  # stuck wheels (and those of dead cells) stay still
        velocities = cells.surface_velocities(wheels)
        if setup.contact_layer is not cells:  # separate or omni wheels, belts: each contact's own surface velocity
            velocities = setup.contact_layer.contact_velocities(velocities)
        return command, wheels, velocities

    def window(self, t0: float, t1: float) -> np.ndarray:
        """The output sample times (s) from ``t0`` to ``t1``, both included where they are on the grid."""
        if self.grid is None:
            return np.array([t0, t1])
        eps = 1e-12 * max(1.0, t1)
        return self.grid[np.searchsorted(self.grid, t0 - eps, side="left"):
                         np.searchsorted(self.grid, t1 + eps, side="right")]  # output samples in this tick

    def carry(self, t0: float, t1: float, velocities: np.ndarray, period: float) -> None:
        """The plant carries every parcel from ``t0`` to ``t1`` (s) under contact ``velocities`` (m/s) held
        (``period``: s, the plant's sample step where no output grid is given); the tracks take it in."""
        window = self.window(t0, t1)
        trajectories, quiet = self.plant.advance_blocks(self.ys, self.active, velocities, t0, t1, period,
                                                        sample_times=window)  # untrimmed: the tracks keep the grid
        self.take_in(trajectories, quiet, window, velocities)

    def take_in(self, trajectories: list, quiet: list, window: np.ndarray, velocities: np.ndarray) -> None:
        """The parcels' tracks take in what the plant returned (:meth:`~virtual_vehicle.engine.plant.Plant.
        advance_blocks`) over an interval whose output samples are ``window`` (s), the Coulomb check runs on them
        under contact ``velocities`` (m/s), and the parcels that left the array are forgotten by the plant."""
        active = self.active
        on: dict[int, np.ndarray] = {}  # by times array: the parcels stepped together share theirs

        def on_window(times):
            if len(window) and id(times) not in on:
                on[id(times)] = on_grid(times, window)
            return on.get(id(times))

        kept = [len(track.times) for track in self.tracks] if self.sliding is not None and len(window) else None
        for i, tr in enumerate(trajectories):
            if tr is not None:
                self.tracks[i].add(tr, window, on_window(tr.times))
        for i, steps, k in quiet:  # those the quiet stepper alone moved, from its block
            self.tracks[i].add_quiet(steps, k, window, on_window(steps.times))
        if kept is not None:
            self._check_sliding(kept, velocities)
        gone = [i for i in self.on if not active[i]]
        for i in gone:  # those that left the array are gone, and so is what was cached for them
            self.plant.release(i)
        if gone:
            self.on = [i for i in self.on if active[i]]

    def parcel_results(self) -> list[ParcelResult]:
        """Every parcel's :class:`ParcelResult` so far: its samples on the grid and its latest state, events, the
        Coulomb check; a parcel not yet on the array is ``"waiting"`` where it will come on."""
        setup = self.setup
        results = []
        for i, (spec, track, y, t) in enumerate(zip(setup.specs, self.tracks, self.ys, self.arrive)):
            traj = track.trajectory() if track.started else Trajectory(np.array([t]), y[None].copy(), [], "waiting", t)
            results.append(ParcelResult(spec, traj, None if self.sliding is None else self.sliding[i],
                                        sliding_checked=self.sliding is not None, entered_at=self.entered[i]))
        return results

    def _check_sliding(self, kept: list[int], velocities: np.ndarray) -> None:
        """The Coulomb check (:func:`coulomb_sliding_check`) on the samples each parcel's track took this tick
        (beyond ``kept`` of them), under this tick's contact ``velocities`` (m/s)."""
        for i, (track, n) in enumerate(zip(self.tracks, kept)):
            if len(track.times) > n:
                found = _sliding(self.setup, self.setup.specs[i], track.times[n:], track.states[n:], velocities)
                if found is not None:
                    before = self.sliding[i]
                    self.sliding[i] = found if before is None else (before[0], max(before[1], found[1]))

    def _inject(self, t: float) -> None:
        """Break what the scenario's fault events due by ``t`` (s) break: from this tick on, dead cells are silent
        and still, stuck wheels held, dead links cut, stuck sensors stuck."""
        events = self.setup.fault_events
        while self.next_fault < len(events) and events[self.next_fault][0] <= t + 1e-9 * max(1.0, t):
            t_event, faults = events[self.next_fault]
            self.next_fault += 1
            self._set_faults(faults)
            self._rewire()
            self.injected.append({"t_s": t_event, "at_tick_s": t, **faults.summary()})

    def _set_faults(self, faults) -> None:
        """The faults from now on, and the sensors they leave (stuck ones stuck); :meth:`_rewire` follows."""
        self.faults = faults
        base = self.setup.sensors
        self.sensors = replace(base, stuck_on=base.stuck_on | faults.stuck_on,
                               stuck_off=(base.stuck_off | faults.stuck_off) & ~(base.stuck_on | faults.stuck_on))

    def _reconfigure(self, t: float) -> None:
        """Take out and snap in the cells the scenario's changes due by ``t`` (s) name: from this tick on a removed
        cell carries, drives, senses and says nothing; an added one starts afresh (:meth:`_cells_added`)."""
        changes = self.setup.cell_changes
        while self.next_change < len(changes) and changes[self.next_change][0] <= t + 1e-9 * max(1.0, t):
            t_change, present = changes[self.next_change]
            self.next_change += 1
            added = present & ~self.present
            removed = self.present & ~present
            self.present = present
            self._rewire()
            self._cells_added(added)
            self.reconfigured.append({"t_s": t_change, "at_tick_s": t, "added": np.flatnonzero(added).tolist(),
                                      "removed": np.flatnonzero(removed).tolist()})

    def _cells_added(self, added: np.ndarray) -> None:
        """Start the cells ``added`` ((n,) bool) afresh: nothing here (an outside decision keeps no cell state)."""

    def _links(self):
        """The cells' topology now: dead and absent cells have no links, dead links are cut."""
        from virtual_vehicle.cells.network.topology import from_layout

        dead = self.faults.dead_cells if self.faults is not None else np.zeros(self.setup.cells.n, dtype=bool)
        links = self.faults.dead_links if self.faults is not None else ()
        if self.present is not None:
            dead = dead | ~self.present
        return from_layout(self.setup.cells).with_faults(dead_cells=np.flatnonzero(dead), dead_links=links)

    def _rewire(self) -> None:
        """The topology and plant after faults or a reconfiguration: dead and absent cells have no links; absent
        cells carry nothing."""
        if self.present is not None:
            self.plant.set_present(self.present[self.setup.contact_layer.cell_of])
        self.topology = self._links()

    def _admit(self, t: float) -> None:
        """Put on the array the parcels due by ``t``, first come first placed, while their place is free: no active
        parcel overlaps it, or, when the program asks for a clearance (config ``clearance``, m), none comes that
        close. The queue waits behind its first parcel."""
        setup = self.setup
        clearance = float(setup.control.config.get("clearance", 0.0)) if setup.control is not None else 0.0
        if self.saturate:
            self._admit_each_place(t, clearance)
            return
        while self.queue and self.arrive[self.queue[0]] <= t + 1e-12:
            i = self.queue[0]
            place = setup.specs[i].world_polygon(self.ys[i])
            for j in self.on:
                other = setup.specs[j].world_polygon(self.ys[j])
                if clearance > 0 and shapely.distance(place, other) <= clearance:
                    return
                if clearance <= 0 and shapely.intersection(place, other).area > 1e-12:
                    return
            self.queue.pop(0)
            self.active[i] = True
            self.entered[i] = t
            self.on = sorted([*self.on, i])

    def _admit_each_place(self, t: float, clearance: float) -> None:
        """Saturated arrivals: each place (a parcel's start pose) keeps its own queue in file order, and its first
        parcel is put on as soon as its place is free (as in :meth:`_admit`), whatever the other places wait for."""
        setup = self.setup
        waiting = set()  # places whose first parcel stays queued
        for i in list(self.queue):
            key = tuple(np.round(self.ys[i][:3], 9))
            if key in waiting:
                continue
            place = setup.specs[i].world_polygon(self.ys[i])
            others = [setup.specs[j].world_polygon(self.ys[j]) for j in self.on]
            waiting.add(key)  # behind this one, or behind the one put on now: one parcel a place a tick
            if clearance > 0 and any(shapely.distance(place, other) <= clearance for other in others):
                continue
            if clearance <= 0 and any(shapely.intersection(place, other).area > 1e-12 for other in others):
                continue
            self.queue.remove(i)
            self.active[i] = True
            self.entered[i] = t
            self.on = sorted([*self.on, i])


class NetworkRun(TickedRun, _Job):
    """The state of a networked run between control ticks: everything needed to go on, so that a long run can be
    checkpointed and resumed bit for bit. Its decision at every tick is the cell programs' and their network's."""

    KIND = "network"
    STATE = ("wall", *TickedRun.TICKED_STATE, "state", "inbox", "inbox_changed", "delivery", "stepper", "per_tick",
             "per_cell", "latency")
    """The ticked run's state (:meth:`TickedRun.ticked_state`), the wall time so far (s), and the network's: the cell
    programs' state (their own tree of arrays and plain values), the inbox they read next, which inboxes changed
    (None: not known), the delivery model's and the changed-cells stepper's state (None without one), the traffic
    per tick and per cell and the latency statistics. The setup, the topology, faults, sensors and cells installed
    now (from :meth:`_position`), the output grid and the arrival times are not state: they follow from the
    setup."""

    def __init__(self, setup: Setup):
        sc = setup.scenario
        ctl = setup.control
        n, P = ctl.topology.n, ctl.topology.ports
        self.scenario_text: str | None = None
        self.wall = 0.0
        self.state = ctl.program.init(n, P, ctl.config)
        self.inbox = Mailbox.empty(ctl.program.schema, n, P)
        self.delivery = ctl.make_delivery()
        # step only the cells that changed, where the program allows it and the delivery model tells which inboxes
        # changed (ideal rounds): the same run to the last bit
        self.stepper = (ChangedCells(ctl.program) if ctl.changed_only and getattr(ctl.program, "stationary", False)
                        and hasattr(self.delivery, "exchange_changed") else None)
        self.inbox_changed: np.ndarray | None = None
        self.destinations = [None if p.destination is None else encode_goal(p.destination, p.sequence)
                             for p in sc.parcels]  # what each parcel's label says
        super().__init__(setup, ctl.period, grid=sample_grid(0.0, sc.duration, sc.output_dt or sc.duration / 500),
                         topology=ctl.topology)  # output sample times, s
        self.ticks = int(np.ceil(sc.duration / self.period - 1e-9))
        keys = ("sent", "received", "bytes_sent", "bytes_received")
        self.per_tick = {k: np.zeros(self.ticks, dtype=np.int64) for k in (*keys, *_FAULTS)}
        self.per_tick["t"] = self.period * np.arange(self.ticks)
        self.per_tick["latency_mean"] = np.full(self.ticks, np.nan)
        self.per_tick["latency_max"] = np.full(self.ticks, np.nan)
        self.per_cell = {f"cell_{k}": np.zeros(n, dtype=np.int64) for k in keys}
        self.latency = LatencyStats()

    def _position(self) -> dict:
        return {"next_fault": self.next_fault, "next_change": self.next_change}

    def _state(self) -> dict:
        return {**self.ticked_state(), "wall": float(self.wall), "state": self.state, "inbox": self.inbox.to_data(),
                "inbox_changed": self.inbox_changed, "delivery": self.delivery.to_data(),
                "stepper": None if self.stepper is None else self.stepper.to_data(),
                "per_tick": self.per_tick, "per_cell": self.per_cell, "latency": self.latency.to_data()}

    def _restore(self, position: dict, state, arrays: list) -> None:
        setup, ctl = self.setup, self.setup.control
        nf, nc = position["next_fault"], position["next_change"]
        if not (type(nf) is int and type(nc) is int and 0 <= nf <= len(setup.fault_events)
                and 0 <= nc <= len(setup.cell_changes)):
            raise ValueError("its fault events or cell changes are not the scenario's")
        if nf or nc:  # the faults and cells of now: what the last event and change made them
            self.next_fault, self.next_change = nf, nc
            if nf:
                self._set_faults(setup.fault_events[nf - 1][1])
            if nc:
                self.present = setup.cell_changes[nc - 1][1]
            self._rewire()
        s = self._read_state(state, arrays)
        self.load_ticked_state(s)
        if self.k > self.most_steps():
            raise ValueError(f"state.k: {self.k} ticks done of the run's {self.most_steps()}")
        _check_like({k: self.__dict__[k] for k in ("state", "per_tick", "per_cell")}, s)
        n, P = self.topology.n, self.topology.ports
        self.wall = number(s, "wall", "state")
        self.state, self.per_tick, self.per_cell = s["state"], s["per_tick"], s["per_cell"]
        self.inbox = Mailbox.from_data(s["inbox"], ctl.program.schema, "state.inbox")
        if self.inbox.present.shape != (n, P):
            raise ValueError(f"state.inbox: shape {self.inbox.present.shape}, not {(n, P)}")
        self.inbox_changed = None if s["inbox_changed"] is None else array(s, "inbox_changed", "b", (n,), "state")
        self.delivery.load_data(s["delivery"], self.inbox)
        if (s["stepper"] is None) != (self.stepper is None):
            raise ValueError("state.stepper: not the scenario's (changed cells only or not)")
        if self.stepper is not None:
            self.stepper.load_data(s["stepper"])
        self.latency = LatencyStats.from_data(s["latency"], "state.latency")

    def most_steps(self) -> int:
        """The most steps (:meth:`tick`) the run takes: its ticks."""
        return self.ticks

    @property
    def done(self) -> bool:
        """True once every control tick has run."""
        return self.k >= self.ticks

    def step(self, every, progress) -> bool:
        """One control tick; True when a checkpoint is due."""
        self.tick()
        if progress is not None:
            progress(self.k / self.ticks)
        return every is not None and self.k % max(1, int(round(every / self.period))) == 0

    def tick(self) -> None:
        """One control tick: :meth:`begin` (faults, cell changes, arrivals, sensors), the cell programs and their
        network decide the wheel speeds, :meth:`finish` (belts, motors, faults, plant)."""
        sensors = self.begin()
        wheels, stats = self._decide(sensors)
        self.finish(wheels, sensors, stats.sent, stats.received)

    def _decide(self, sensors: np.ndarray):
        """The decision of this tick: every cell steps its program on its ``sensors``, its inbox and its parcel's
        label, and sends; the network delivers. Returns the (n, 2) wheel speeds the programs ask for (m/s) and the
        delivery's traffic statistics of the tick (also added to the network record)."""
        setup, ctl = self.setup, self.setup.control
        k, period = self.k, self.period
        t0, _ = self.span()
        topo = self.topology
        ys, on = self.ys, self.on
        labelled = any(self.destinations[i] is not None for i in on)
        labels = _labels(setup, [ys[i] for i in on], [setup.specs[i] for i in on],
                         [self.destinations[i] for i in on]) if labelled else None
        inputs = CellInputs(t0, sensors, self.inbox, topo.connected, self._program_config(), labels)
        if self.stepper is None:
            self.state, outbox, wheels = ctl.program.step(self.state, inputs)
            self.inbox, stats = self.delivery.exchange(outbox, t0, period)  # what they sent, delivered
        else:  # only the cells that changed step; the network tells whose inbox changes
            self.state, outbox, wheels, out_changed = self.stepper.step(self.state, inputs, self.inbox_changed)
            self.inbox, stats, self.inbox_changed = self.delivery.exchange_changed(outbox, out_changed, t0, period)
        for key in ("sent", "received", "bytes_sent", "bytes_received"):
            self.per_tick[key][k] = int(getattr(stats, key).sum())
            self.per_cell[f"cell_{key}"] += getattr(stats, key)
        for key in _FAULTS:
            self.per_tick[key][k] = getattr(stats, key)
        if len(stats.latencies):
            self.per_tick["latency_mean"][k] = stats.latencies.mean()
            self.per_tick["latency_max"][k] = stats.latencies.max()
            self.latency.add(stats.latencies)
        return wheels, stats

    def _cells_added(self, added: np.ndarray) -> None:
        """The cells ``added`` start their program afresh."""
        ctl = self.setup.control
        fresh = ctl.program.init(self.topology.n, self.topology.ports, ctl.config)
        self.state = _reset_rows(self.state, fresh, added)

    def _rewire(self) -> None:
        """:meth:`TickedRun._rewire`, and the delivery model on the new topology."""
        super()._rewire()
        self.delivery.set_topology(self.topology)

    def _program_config(self) -> dict:
        """The cells' configuration now: the scenario's, with the sorter's ``inner`` ports (a silent neighbour there
        is a dead cell that still carries a parcel, :mod:`~virtual_vehicle.cells.sorting`) kept only where that
        neighbour and the cell beyond it are in place: a cell taken out is a hole, not a dead cell."""
        config = self.setup.control.config
        if self.present is None or "inner" not in config:
            return config
        made = getattr(self, "_config_now", None)
        if made is None or made[0] is not self.present:
            nb = self.topology.neighbor  # every neighbour the layout has, in place or not
            inner = np.asarray(config["inner"], dtype=bool).copy()
            beyond = nb[np.maximum(nb, 0), np.arange(nb.shape[1])]  # the cell beyond it the same way
            inner &= (nb >= 0) & self.present[np.maximum(nb, 0)] & (beyond >= 0) & self.present[np.maximum(beyond, 0)]
            made = self._config_now = (self.present, {**config, "inner": inner})
        return made[1]

    def result(self) -> RunResult:
        """The run's :class:`RunResult`: trajectories, network record and (when recorded) the cell log."""
        setup, ctl = self.setup, self.setup.control
        results = self.parcel_results()
        record = NetworkRecord(ctl.delivery_name, self.period, self.per_tick, self.per_cell, self.latency)
        stats = {"network": record.totals(), "plant": plant_totals(self.plant)}
        if self.injected:
            stats["faults_injected"] = self.injected
        if self.reconfigured:
            stats["reconfigured"] = self.reconfigured
        return RunResult(setup, results, self.wall, stats,
                         record, CellLog.stack(self.cell_log) if setup.scenario.sensors.record and self.cell_log else None,
                         self.scenario_text, self.state, self.topology)


def _labels(setup: Setup, states, specs, destinations) -> np.ndarray:
    """(n,) the destination label of the parcel above each cell's centre, -1 for none (``states``, ``specs`` and
    ``destinations`` of the parcels on the array)."""
    cells = setup.cells
    out = np.full(cells.n, -1, dtype=np.int64)
    on = [k for k, dest in enumerate(destinations) if dest is not None]
    if on:
        owner, cell = covered_pairs([specs[k] for k in on], [states[k] for k in on], cells.grid)
        out[cell] = np.array([destinations[k] for k in on], dtype=np.int64)[owner]
    return out
