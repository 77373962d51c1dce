"""The Simulator: runs a validated scenario and records what happened to every parcel.

Units: SI. A constant field is run as one plant interval; a networked run advances the plant one control tick at a time.
The plant (:mod:`virtual_vehicle.engine.plant`) integrates each parcel on its own while it cannot meet another and
resolves contact between parcels when it can.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import shapely

from virtual_vehicle import __version__
from virtual_vehicle.cells.hardware import WheelDrives
from virtual_vehicle.cells.network.messages import Mailbox
from virtual_vehicle.cells.network.clocks import CellClocks, Mailboxes
from virtual_vehicle.cells.network.programs import CellInputs, ChangedCells, step_group, tree_map
from virtual_vehicle.cells.network.topology import Topology
from virtual_vehicle.cells.programs import program_of
from virtual_vehicle.cells.sorting import encode_goal
from virtual_vehicle.config.scenario import Setup
from virtual_vehicle.engine.dynamics import Trajectory, sample_grid
from virtual_vehicle.engine.stepping import Event
from virtual_vehicle.engine.plant import SUMMED_STATS, join, joined_stats, on_grid
from virtual_vehicle.errors import VirtualVehicleError
from virtual_vehicle.model.parcel import ParcelSpec, covered_pairs, supporting_cells
from virtual_vehicle.model.state_data import array, fields, integer, number, rng_from_data, rng_to_data

_ENERGY = ("kinetic_start", "kinetic_end", "wheel_work", "friction_dissipation", "step_dissipation", "contact_work")


@dataclass
class ParcelResult:
    """One parcel's run. ``sliding_violation`` is, for the Coulomb law, the first sample time (s) at which some
    supporting wheel no longer slid under the parcel in its direction of spin (the paper's Coulomb assumption), and
    the largest reversed slip (m/s) seen; None when the assumption held at every sample or was not checked
    (``sliding_checked`` False: another law, or a run that could not check it). Networked runs check it at every
    output sample against the wheel speeds of that control tick."""

    spec: ParcelSpec
    trajectory: Trajectory
    sliding_violation: tuple[float, float] | None = None
    sliding_checked: bool = True
    entered_at: float | None = 0.0
    """When the parcel was put on the array (s); None if its place never came free (status ``"waiting"``)."""


@dataclass
class CellLog:
    """What every cell saw and did at every control tick (T ticks, n cells, S sensors per cell).

    ``t`` (T,) tick start, s; ``readings`` (T, n, S) presence sensors, bool; ``wheels`` (T, n, 2) the wheels' mean
    surface speeds over the tick and ``commands`` (T, n, 2) the speeds the cell program asked for, m/s (wheel 0
    along the cell's first drive direction); ``sent`` / ``received`` (T, n) sentences each cell put on and took off
    its links during the tick."""

    t: np.ndarray
    readings: np.ndarray
    wheels: np.ndarray
    commands: np.ndarray
    sent: np.ndarray
    received: np.ndarray

    @classmethod
    def stack(cls, rows: list[tuple]) -> "CellLog":
        """From per-tick rows (t, readings, wheels, commands, sent, received)."""
        cols = list(zip(*rows))
        return cls(*(np.asarray(c) for c in cols))


@dataclass
class RunResult:
    """Everything a run produced."""

    setup: Setup
    parcels: list[ParcelResult]
    wall_time: float
    stats: dict = field(default_factory=dict)
    network: "NetworkRecord | None" = None
    cell_log: "CellLog | None" = None
    """Every cell at every control tick, when recording was asked (``[sensors] record = true``, networked runs)."""
    scenario_text: str | None = None
    """The scenario file's text, when the run was started from one (kept through checkpoints)."""
    program_state: dict | None = None
    """The cell program's state at the run's end (networked runs), with ``topology`` its links then: what the
    program's report reads a deadlock from (who waits on whom, :mod:`virtual_vehicle.cells.sorting.holds`)."""
    topology: Topology | None = None

    def summary(self) -> dict:
        """A JSON-ready summary: per-parcel outcome, start/end state, distance, events; run totals."""
        sc, law = self.setup.scenario, self.setup.law
        parcels = []
        for pr in self.parcels:
            tr = pr.trajectory
            path = np.diff(tr.states[:, :2], axis=0)
            parcels.append({
                "name": pr.spec.name,
                "status": tr.status,
                "t_end_s": tr.t_end,
                "start": dict(zip(("x", "y", "theta", "vx", "vy", "omega"), map(float, tr.states[0]))),
                "end": dict(zip(("x", "y", "theta", "vx", "vy", "omega"), map(float, tr.states[-1]))),
                "path_length_m": float(np.sum(np.hypot(path[:, 0], path[:, 1]))) if len(path) else 0.0,
                "support_changes": sum(1 for e in tr.events if e.kind == "support"),
                "tipped_at_s": next((e.t for e in tr.events if e.kind == "tip"), None),
                "contacts_with_parcels": sum(1 for e in tr.events if e.kind == "contact"),
                "segments": tr.segments,
                "rhs_evaluations": tr.rhs_evals,
                "chatter_steps": tr.stats.get("chatter_steps", 0),  # fixed steps across a sliding mode (event mode)
                "coulomb_sliding_assumption_violated_at_s": pr.sliding_violation[0] if pr.sliding_violation else None,
                "coulomb_max_reversed_slip_m_per_s": pr.sliding_violation[1] if pr.sliding_violation else None,
                "coulomb_sliding_checked": pr.sliding_checked and self.setup.law.assumes_sliding,
                **({"energy_J": {k: tr.stats[k] for k in _ENERGY},
                    "stick_slip_unconverged_steps": tr.stats["unconverged_steps"],
                    "stick_slip_mode_changes": tr.stats.get("mode_changes", 0)} if "wheel_work" in tr.stats else {}),
            })
        extra = {}
        task = None if sc.control is None else program_of(sc.control)
        if task is not None and task.report is not None:  # the program's task report, its rows merged per parcel
            report = task.report(self)
            for entry, row in zip(parcels, report.pop("parcels")):
                entry.update({k: v for k, v in row.items() if k != "name"})
            extra[task.SUMMARY] = report
        faults = self.setup.faults
        if faults is not None and faults.any():
            extra["faults"] = faults.summary()
        simulated = sum(pr.trajectory.t_end for pr in self.parcels)
        checked = [p for p in parcels if p["coulomb_sliding_checked"]]
        violated = [p for p in checked if p["coulomb_sliding_assumption_violated_at_s"] is not None]
        extra["coulomb_sliding"] = {  # the paper's Coulomb law assumes every wheel slides under the parcel (4.3)
            "checked": bool(checked),
            "parcels_violating": len(violated),
            "first_violation_s": min((p["coulomb_sliding_assumption_violated_at_s"] for p in violated), default=None),
            "max_reversed_slip_m_per_s": max((p["coulomb_max_reversed_slip_m_per_s"] for p in violated),
                                             default=None),
        }
        return {
            "scenario": sc.name,
            "version": __version__,
            "friction_law": sc.friction.law,
            "integrator": (f"time-stepping ({law.time_stepper.replace('_', '-')})"
                           if law.time_stepper and (sc.integrator.mode == "fixed" or not law.modes)
                           else sc.integrator.mode),
            "duration_s": sc.duration,
            "cells": self.setup.cells.n,
            "parcels": parcels,
            "wall_time_s": self.wall_time,
            "real_time_factor": (sc.duration / self.wall_time) if self.wall_time > 0 else None,
            "parcel_seconds_simulated": simulated,
            **self.stats,
            **extra,
        }

    def to_pandas(self) -> dict:
        """The run's tables (:func:`virtual_vehicle.run.tables.build`) as pandas DataFrames, by table name:
        ``trajectories`` and ``events`` always, ``network`` and ``cell_traffic`` for networked runs, ``cells`` when
        recorded. Each frame keeps its columns' SI units in ``df.attrs["units"]`` (column -> unit, ``""`` for
        counts, ids and flags). Needs pandas (an optional dependency; the ``dev`` extra installs it)."""
        try:
            import pandas  # noqa: F401  (pyarrow's to_pandas needs it)
        except ImportError as exc:
            raise ImportError("RunResult.to_pandas needs pandas, which is not installed: pip install pandas") from exc
        from virtual_vehicle.run import tables

        frames = {}
        for name, table in tables.build(self).items():
            df = table.to_pandas()
            df.attrs["units"] = {f.name: f.metadata[b"unit"].decode() for f in table.schema}
            frames[name] = df
        return frames


def coulomb_sliding_check(setup: Setup, spec: ParcelSpec, traj: Trajectory,
                          velocities: np.ndarray | None = None) -> tuple[float, float] | None:
    """Check the paper's Coulomb assumption (Section 4.3: every wheel slides under the parcel in its direction of
    spin) at every sample: under each supporting cell, each spinning wheel's surface speed along its drive direction
    exceeds the parcel's. ``velocities``: the contact layer's surface velocities (m/s) over the samples (default the
    constant field's). Returns (first violating time s, largest reversed slip m/s) or None."""
    return _sliding(setup, spec, traj.times, traj.states,
                    setup.contact_velocities if velocities is None else velocities)


def _sliding(setup: Setup, spec: ParcelSpec, times, states, velocities: np.ndarray) -> tuple[float, float] | None:
    """:func:`coulomb_sliding_check` on the samples ``times`` (s) and ``states``."""
    cells = setup.contact_layer
    first, worst = None, 0.0
    for t, y in zip(times, states):
        ids = supporting_cells(spec, y, cells.positions, cells.tree)
        if len(ids) == 0:
            continue
        r = cells.positions[ids] - y[:2]
        w = y[3:5] + y[5] * np.column_stack([-r[:, 1], r[:, 0]])  # parcel velocity over each cell
        U = cells.active_directions[ids]
        wheel = np.einsum("ij,ikj->ik", velocities[ids], U)
        parcel = np.einsum("ij,ikj->ik", w, U)
        reversed_slip = np.where(wheel != 0, -np.sign(wheel) * (wheel - parcel), -np.inf)
        m = float(reversed_slip.max())
        if m > 1e-9:
            first = float(t) if first is None else first
            worst = max(worst, m)
    return None if first is None else (first, worst)


def run(setup: Setup, progress: Callable[[float], None] | None = None, *,
        checkpoint: str | Path | None = None, checkpoint_every: float | None = None,
        scenario_text: str | None = None) -> RunResult:
    """Run a built scenario. ``progress`` is called with the fraction of the run done (0..1). A scenario with a
    ``[control]`` table is co-simulated with its cell program and network (:func:`run_network`); a constant field
    is one plant interval, cut at every checkpoint when ``checkpoint`` (a file path) and ``checkpoint_every``
    (simulated s) are given, and :func:`resume` continues it to exactly the result the same checkpointed run gives
    uninterrupted."""
    if setup.control is not None:
        return run_network(setup, progress, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                           scenario_text=scenario_text)
    job = FieldRun(setup)
    job.scenario_text = scenario_text
    return job.run(progress, checkpoint=checkpoint, checkpoint_every=checkpoint_every)


class _Job:
    """A run that can be cut into steps, checkpointed between them and resumed (subclasses: :class:`FieldRun`,
    :class:`NetworkRun`). ``step`` advances and says whether a checkpoint is due; ``result`` finishes."""

    version: str
    wall: float

    @property
    def done(self) -> bool:
        raise NotImplementedError

    def step(self, every: float | None, progress) -> bool:
        raise NotImplementedError

    def result(self) -> RunResult:
        raise NotImplementedError

    def run(self, progress=None, *, checkpoint=None, checkpoint_every=None) -> RunResult:
        """Step to the end (writing checkpoints when asked) and return the result."""
        if checkpoint is not None and not (checkpoint_every and 0 < checkpoint_every < math.inf):
            raise VirtualVehicleError(f"checkpoint_every: must be a positive, finite number of simulated seconds, got "
                                      f"{checkpoint_every}")
        every = None if checkpoint is None else float(checkpoint_every)
        start = time.perf_counter()
        while not self.done:
            due = self.step(every, progress)
            if due and not self.done:
                self.wall += time.perf_counter() - start
                start = time.perf_counter()
                self.save(checkpoint, every)
        self.wall += time.perf_counter() - start
        if progress is not None:
            progress(1.0)
        return self.result()

    KIND: str
    """The run's kind as a checkpoint names it."""

    def save(self, path, checkpoint_every: float) -> None:
        """Write this run's state to ``path`` atomically (a data file, see :mod:`virtual_vehicle.run.checkpoint`), then
        go on from exactly what :func:`resume` reads back from it (caches start afresh), so that the checkpointed
        run and one resumed from any of its checkpoints are the same run to the last bit."""
        from virtual_vehicle.run.files import write_atomic

        data = self.checkpoint_bytes(checkpoint_every)
        write_atomic(Path(path), data)
        fresh, _ = _load(data, setup=self.setup)
        self.__dict__.update(fresh.__dict__)

    STATE: tuple[str, ...]
    """The fields that are the run's state, each written as data (arrays and plain values) by :meth:`_state` and
    read back by :meth:`_restore`. Everything else a run holds is its model (the setup, immutable), what follows
    from the setup and :meth:`_position`, or a cache made again as needed."""

    def checkpoint_bytes(self, checkpoint_every: float) -> bytes:
        """This run's checkpoint: its scenario, where it is (:meth:`_position`, plain JSON) and its state
        (:attr:`STATE` as data, :meth:`_state`, encoded by :mod:`virtual_vehicle.run.checkpoint`); never the setup
        or any cache."""
        from virtual_vehicle.run.checkpoint import FORMAT_VERSION, encode, pack

        state = self._state()
        if set(state) != set(self.STATE):
            raise AssertionError(f"the state written is not the state declared: {sorted(set(state) ^ set(self.STATE))}")
        tree, arrays = encode(state)
        document = {"format_version": FORMAT_VERSION, "package_version": __version__, "kind": self.KIND,
                    "checkpoint_every": float(checkpoint_every), "scenario": self.setup.scenario.model_dump(mode="json"),
                    "scenario_text": self.scenario_text, "setup_digest": _setup_digest(self.setup),
                    "position": self._position(), "state": tree}
        return pack(document, arrays)

    def _position(self) -> dict:
        return {}

    def _state(self) -> dict:
        """The fields of :attr:`STATE` as data, by name."""
        raise NotImplementedError

    def _restore(self, position: dict, state, arrays: list) -> None:
        """Take up a checkpoint's position and state (its document's tree and arrays) on this run, made afresh from
        the same setup; raises ValueError (or CheckpointError) for a state that does not fit it."""
        raise NotImplementedError

    def _read_state(self, state, arrays: list) -> dict:
        """The checkpoint's state tree decoded, checked to hold exactly the fields of :attr:`STATE`."""
        from virtual_vehicle.run.checkpoint import decode

        s = decode(state, arrays)
        if type(s) is not dict or set(s) != set(self.STATE):
            got = sorted(map(str, s)) if type(s) is dict else type(s).__name__
            raise ValueError(f"it holds {got}, not the state of a {self.KIND} run {sorted(self.STATE)}")
        return s


class FieldRun(_Job):
    """A constant-field run between checkpoints: the plant, every parcel's state and the pieces of trajectory so
    far."""

    KIND = "field"

    def __init__(self, setup: Setup):
        sc = setup.scenario
        self.scenario_text: str | None = None
        self.setup = setup
        self.t = 0.0
        self.wall = 0.0
        self.grid = sample_grid(0.0, sc.duration, sc.output_dt or sc.duration / 500)  # output sample times, s
        self.plant = setup.plant()
        self.ys = [y.copy() for y in setup.states]
        self.active = [True] * len(self.ys)
        self.parts: list[list[Trajectory]] = [[] for _ in self.ys]

    @property
    def done(self) -> bool:
        """True once the plant has reached the scenario's duration."""
        return self.t >= self.setup.scenario.duration

    def step(self, every, progress) -> bool:
        """Advance to the next checkpoint (or the end); True when a checkpoint is due."""
        t_end = self.setup.scenario.duration
        t0 = self.t
        t1 = t_end if every is None or t0 + every >= t_end - 1e-9 * every else t0 + every
        eps = 1e-12 * max(1.0, t1)
        inside = self.grid[np.searchsorted(self.grid, t0 + eps, side="right"):
                           np.searchsorted(self.grid, t1 - eps, side="left")]
        window = np.concatenate([[t0], inside, [t1]])  # the pieces meet at the cuts; join drops the repeats
        report = None if progress is None else (lambda t: progress(t / t_end))
        for part, tr in zip(self.parts, self.plant.advance(self.ys, self.active, self.setup.contact_velocities,
                                                           t0, t1, 0.0, report, sample_times=window)):
            if tr is not None:
                part.append(tr)
        self.t = t1
        return True

    STATE = ("t", "wall", "ys", "active", "parts", "plant")
    """The plant's time and the wall time so far (s), every parcel's state (N, 6) and whether it is still on the
    array, the pieces of trajectory so far (:meth:`Trajectory.to_data` each), the plant's state."""

    def _state(self) -> dict:
        return {"t": float(self.t), "wall": float(self.wall), "ys": _stack(self.ys),
                "active": np.array(self.active, dtype=bool), "parts": [[tr.to_data() for tr in part] for part in
                                                                        self.parts],
                "plant": self.plant.state()}

    def _restore(self, position: dict, state, arrays: list) -> None:
        s = self._read_state(state, arrays)
        N = len(self.setup.specs)
        parts = s["parts"]
        if type(parts) is not list or len(parts) != N or not all(type(p) is list for p in parts):
            raise ValueError("state.parts: not a list of pieces per parcel")
        self.parts = [[Trajectory.from_data(d, f"state.parts[{i}]") for d in part] for i, part in enumerate(parts)]
        self.t, self.wall = number(s, "t", "state"), number(s, "wall", "state")
        self.ys = [row.copy() for row in array(s, "ys", "f", (N, 6), "state")]
        self.active = array(s, "active", "b", (N,), "state").tolist()
        self.plant.restore(s["plant"])

    def result(self) -> RunResult:
        """Join the pieces into the run's :class:`RunResult` (samples on the output grid, and each parcel's last)."""
        setup = self.setup
        results = []
        for spec, part in zip(setup.specs, self.parts):
            traj = join(part)
            keep = np.isin(traj.times, self.grid)  # the output samples, wherever the checkpoints cut
            keep[-1] = True
            traj = replace(traj, times=traj.times[keep], states=traj.states[keep])
            check = coulomb_sliding_check(setup, spec, traj) if setup.law.assumes_sliding else None
            results.append(ParcelResult(spec, traj, check))
        return RunResult(setup, results, self.wall, {"plant": plant_totals(self.plant)},
                         scenario_text=self.scenario_text)


def plant_totals(plant) -> dict:
    """The plant's run-level record, JSON-ready."""
    rec = plant.record
    return {"parcel_contacts": rec.parcel_contacts, "max_penetration_m": rec.max_penetration_m,
            "undetected_overlaps": rec.undetected_overlaps, "grouped_steps": rec.grouped_steps,
            "unconverged_contact_steps": rec.unconverged_contact_steps, "windows": rec.windows,
            "quiet_steps": rec.quiet_steps}


class LatencyStats:
    """Streaming statistics of sentence latencies (s): count, sum, min, max, and counts on 512 log-spaced bins from
    1 microsecond to 1000 s (edges 4.1% apart) for percentiles, so that an hour's run does not keep every one."""

    EDGES = np.logspace(-6, 3, 513)

    def __init__(self):
        self.count = 0
        self.total = 0.0
        self.min = np.inf
        self.max = -np.inf
        self.counts = np.zeros(512, dtype=np.int64)

    def add(self, latencies: np.ndarray) -> None:
        """Count more sentence latencies (s)."""
        if not len(latencies):
            return
        self.count += len(latencies)
        self.total += float(latencies.sum())
        low, high = float(latencies.min()), float(latencies.max())
        self.min = min(self.min, low)
        self.max = max(self.max, high)
        if low == high:  # all in one bin (on ideal rounds every sentence takes one period)
            self.counts[min(max(int(np.searchsorted(self.EDGES, low, side="right")) - 1, 0), 511)] += len(latencies)
            return
        bins = np.clip(np.searchsorted(self.EDGES, latencies, side="right") - 1, 0, 511)
        self.counts += np.bincount(bins, minlength=512)

    @property
    def mean(self) -> float | None:
        """Mean latency, s (None before any)."""
        return self.total / self.count if self.count else None

    def percentile(self, q: float) -> float | None:
        """The upper edge of the bin holding the q-th percentile (within 4.1%), clipped to [min, max]."""
        if not self.count:
            return None
        k = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.count, side="left"))
        return float(min(max(self.EDGES[min(k + 1, 512)], self.min), self.max))

    def to_data(self) -> dict:
        """These statistics as data: ``count``, ``total`` (s), ``min`` and ``max`` (s, infinite before any) and the
        bins' ``counts`` (512,)."""
        return {"count": int(self.count), "total": float(self.total), "min": float(self.min), "max": float(self.max),
                "counts": self.counts}

    @classmethod
    def from_data(cls, d, where: str = "latency") -> "LatencyStats":
        """The statistics :meth:`to_data` wrote; raises ValueError for data of other keys, kinds or shapes."""
        d = fields(d, ("count", "total", "min", "max", "counts"), where)
        out = cls()
        out.count, out.total = integer(d, "count", where), number(d, "total", where)
        out.min, out.max = number(d, "min", where), number(d, "max", where)
        out.counts = array(d, "counts", "i", (512,), where)
        if int(out.counts.sum()) != out.count:
            raise ValueError(f"{where}: its bins do not add up to its count")
        return out

    def __eq__(self, other) -> bool:
        return (isinstance(other, LatencyStats) and self.count == other.count and self.total == other.total
                and self.min == other.min and self.max == other.max and np.array_equal(self.counts, other.counts))


@dataclass
class NetworkRecord:
    """Message traffic of a networked run.

    Per tick (arrays of length ticks): ``t`` (s), ``sent``, ``received``, ``bytes_sent``, ``bytes_received``,
    ``lost``, ``corrupted``, ``undetected``, ``dropped``, ``latency_mean`` / ``latency_max`` (s, NaN when nothing
    arrived). Per cell (arrays of length n): ``cell_sent``, ``cell_received``, ``cell_bytes_sent``,
    ``cell_bytes_received``. ``latency``: the delivered sentences' latencies (:class:`LatencyStats`).
    """

    delivery: str
    period: float
    per_tick: dict[str, np.ndarray]
    per_cell: dict[str, np.ndarray]
    latency: LatencyStats

    def totals(self) -> dict:
        """Run totals for the summary: sentences, bytes, faults, latency statistics (s)."""
        lat = self.latency
        return {
            "delivery": self.delivery,
            "control_period_s": self.period,
            "sentences_sent": int(self.per_tick["sent"].sum()),
            "sentences_received": int(self.per_tick["received"].sum()),
            "bytes_sent": int(self.per_tick["bytes_sent"].sum()),
            "lost": int(self.per_tick["lost"].sum()),
            "corrupted": int(self.per_tick["corrupted"].sum()),
            "undetected_corruptions": int(self.per_tick["undetected"].sum()),
            "dropped": int(self.per_tick["dropped"].sum()),
            "unaddressed": int(self.per_tick["unaddressed"].sum()),
            "latency_mean_s": lat.mean,
            "latency_p95_s": lat.percentile(95),
            "latency_max_s": lat.max if lat.count else None,
        }


_FAULTS = ("lost", "corrupted", "undetected", "dropped", "unaddressed")

_CELL_LOG = ("t", "readings", "wheels", "commands", "sent", "received")
"""The columns of a ticked run's cell log, as :class:`CellLog` names them."""


def _stack(states: list[np.ndarray]) -> np.ndarray:
    """Parcels' states (each (6,)) as one (N, 6) float array."""
    return np.array(states, dtype=np.float64).reshape(len(states), 6)


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


def run_network(setup: Setup, progress: Callable[[float], None] | None = None, *,
                checkpoint: str | Path | None = None, checkpoint_every: float | None = None,
                scenario_text: str | None = None) -> RunResult:
    """Co-simulate cell programs, the network and the parcels: at every control tick the cells read their sensors
    and the sentences delivered since the last tick, step their program, and send; the wheels hold the commanded
    speeds until the next tick (zero-order hold) while the plant integrates every parcel (event-driven).

    With ``checkpoint`` (a file path) and ``checkpoint_every`` (simulated s), the whole run's state is written there
    (atomically) that often; :func:`resume` continues from it to exactly the result an uninterrupted run gives.
    """
    job = network_job(setup)
    job.scenario_text = scenario_text
    return job.run(progress, checkpoint=checkpoint, checkpoint_every=checkpoint_every)


def resume(checkpoint: str | Path, progress: Callable[[float], None] | None = None, *,
           checkpoint_every: float | None = None) -> RunResult:
    """Continue a run from its last checkpoint (see :func:`run` and :func:`run_network`); by default it keeps writing
    checkpoints to the same file as often as before. Raises VirtualVehicleError, with one message, for a file that is
    not a checkpoint, is damaged, or was written by another format or package version.

    A checkpoint is data (:mod:`virtual_vehicle.run.checkpoint`): reading one never runs code named by the file. The
    run's setup is built again from the scenario it holds."""

    path = Path(checkpoint)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise VirtualVehicleError(f"cannot read checkpoint {path}: {exc.strerror or exc}") from None
    job, every = _load(data, where=str(path))
    return job.run(progress, checkpoint=path, checkpoint_every=checkpoint_every or every)


def carry_on(job: "_Job", setup: Setup) -> "_Job":
    """A run of ``setup`` (of ``job``'s own class) that takes up exactly where ``job`` is, through its checkpoint
    state: for a setup that differs from the job's only in what has not happened yet (fault events after now), as a
    viewer records a fault while the run goes on. Raises VirtualVehicleError for a state that does not fit."""
    from virtual_vehicle.run.checkpoint import CheckpointError, unpack

    document, arrays = unpack(job.checkpoint_bytes(1.0))
    fresh = type(job)(setup)
    fresh.scenario_text = job.scenario_text
    try:
        fresh._restore(document["position"], document["state"], arrays)
    except (CheckpointError, KeyError, TypeError, ValueError) as exc:
        raise VirtualVehicleError(f"the run cannot go on under the changed scenario: {exc}") from None
    return fresh


def _load(data: bytes, setup: Setup | None = None, where: str = "checkpoint") -> tuple["_Job", float]:
    """The run a checkpoint's bytes hold and its checkpoint interval (s). ``setup``: the run's own (a checkpointing
    run going on from what it wrote); None: built from the checkpoint's scenario. Raises VirtualVehicleError."""
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.checkpoint import CheckpointError, unpack

    try:
        document, arrays = unpack(data)
    except CheckpointError as exc:
        raise VirtualVehicleError(f"cannot resume {where}: {exc}") from None
    version = document.get("package_version")
    if version != __version__:
        raise VirtualVehicleError(f"cannot resume {where}: it was written by virtual_vehicle {version}; this is "
                                  f"{__version__} (resume it with {version}, or run the scenario again)")
    kinds = {"field": FieldRun, "network": NetworkRun, "clocked": ClockedRun}
    kind, every = document.get("kind"), document.get("checkpoint_every")
    if kind not in kinds or type(every) is not float or not 0 < every < math.inf or type(document.get("position")) is not dict:
        raise VirtualVehicleError(f"cannot resume {where}: damaged (its run kind, interval or position)")
    if setup is None:
        try:
            setup = parse_scenario(document.get("scenario")).build()
        except VirtualVehicleError as exc:
            raise VirtualVehicleError(f"cannot resume {where}: its scenario: {exc}") from None
        if document.get("setup_digest") != _setup_digest(setup):
            raise VirtualVehicleError(f"cannot resume {where}: its scenario builds another setup than the run had (a "
                                      "setup changed after it was built cannot be resumed)")
    if kind != (FieldRun if setup.control is None else type(network_job(setup))).KIND:
        raise VirtualVehicleError(f"cannot resume {where}: a {kind} run's checkpoint whose scenario is not one")
    job = kinds[kind](setup)
    text = document.get("scenario_text")
    job.scenario_text = text if type(text) is str else None
    try:
        job._restore(document["position"], document.get("state"), arrays)
    except (CheckpointError, KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError,
            RecursionError, MemoryError) as exc:
        raise VirtualVehicleError(f"cannot resume {where}: its state does not fit its scenario "
                                  f"({type(exc).__name__}: {exc})") from None
    return job, every


def _setup_digest(setup: Setup) -> str:
    """A SHA-256 of what a run's setup starts from (wheel velocities, contact positions, parcels' start states and
    bodies), so that a resume whose scenario builds another setup than the run had is refused, not run."""
    import hashlib

    h = hashlib.sha256()
    for a in (setup.velocities, setup.contact_layer.positions, np.array(setup.states, dtype=float).reshape(-1, 6),
              np.array([[s.mass, s.inertia, s.mu, s.radius] for s in setup.specs], dtype=float).reshape(-1, 4)):
        a = np.ascontiguousarray(a, dtype=float)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


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


def network_job(setup: Setup) -> "NetworkRun":
    """The run of a networked scenario: its cells on one shared clock (:class:`NetworkRun`) or each on its own
    (:class:`ClockedRun`, a scenario with ``[control.clock]`` drift or jitter)."""
    return NetworkRun(setup) if setup.control.clock is None else ClockedRun(setup)


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


_SUMMED = frozenset(SUMMED_STATS)


class ParcelTrack:
    """One parcel's trajectory as a networked run goes: only the samples on the output grid and the latest state
    are kept (a run of an hour at 100 Hz would otherwise hold a piece per tick), events, status and the energy and
    solver counts (added up as :func:`~virtual_vehicle.engine.plant.join` does)."""

    def __init__(self):
        self.times: list[float] = []
        self.states: list[np.ndarray] = []
        self.events: list = []
        self._piece = None  # the latest piece, whose last state, status, end and stats carry on
        self._quiet = None  # or (steps, k): the latest piece was a quiet step, not yet made a Trajectory
        self.segments = 0
        self.rhs_evals = 0
        self.stats_pieces: list[dict] = []

    def settle(self) -> None:
        """Make the latest piece and the stats piece Trajectories if they are still kept as quiet steps (a checkpoint
        writes Trajectories, not the stepper's blocks)."""
        self.piece
        self._stats_first()

    @property
    def piece(self) -> Trajectory | None:
        """The latest piece (None before the first)."""
        if self._quiet is not None:
            steps, k = self._quiet
            self._piece, self._quiet = steps.trajectory(k), None
        return self._piece

    @property
    def started(self) -> bool:
        """Whether the track has taken in a tick yet."""
        return self._piece is not None or self._quiet is not None

    def _sample(self, times: np.ndarray, states: np.ndarray) -> None:
        """Keep the samples at ``times`` (s, on the output grid) with their ``states`` (an array of this track's own,
        whose rows it keeps) after the last kept."""
        for t, y in zip(times.tolist(), states):
            if not self.times or t > self.times[-1]:
                self.times.append(t)
                self.states.append(y)

    def add(self, tr: Trajectory, grid: np.ndarray, on: np.ndarray | None = None) -> None:
        """Take in the parcel's trajectory over one tick (as the plant returns it untrimmed): of its samples, those
        on the output ``grid`` (s) and its last state. ``on``: which of its times lie on the grid, when known."""
        if len(grid):  # most control ticks hold no output sample
            if on is None:
                on = on_grid(tr.times, grid)
            self._sample(tr.times[on], tr.states[on])
        self.events.extend(tr.events)
        self.segments += tr.segments
        self.rhs_evals += tr.rhs_evals
        self._piece, self._quiet = tr, None
        if tr.stats:
            first = self._stats_first()
            if first and not (_SUMMED.isdisjoint(tr.stats) and _SUMMED.isdisjoint(first[0].stats)):
                self.stats_pieces = join_stats([*first, tr])
            else:
                self.stats_pieces = [tr]  # the latest stands

    def add_quiet(self, steps, k: int, grid: np.ndarray, on: np.ndarray | None = None) -> None:
        """:meth:`add` for a tick the quiet stepper alone took, as ``steps.trajectory(k)`` (one step, no events, the
        stats the count of solves only; or a ride, ``steps.summed``: its stats joined when read), without making that
        Trajectory unless it is asked for."""
        if len(grid):
            if on is None:
                on = on_grid(steps.times, grid)
            self._sample(steps.times[on], steps.states[steps.rows[k], on])
        self.segments += 1
        self.rhs_evals += steps.evals
        self._quiet = ref = steps, k
        if steps.summed:
            self._add_ride_stats(steps, k)
            return
        head = self.stats_pieces[0] if self.stats_pieces else None
        if type(head) is _RideJoin:
            head = self._stats_first()[0]
        if head is not None and type(head) is not tuple and not _SUMMED.isdisjoint(head.stats):
            self.stats_pieces = join_stats([head, self.piece])  # (a quiet step's own stats hold nothing summed)
        else:
            self.stats_pieces = [ref]  # the latest stands, made a Trajectory when it is read

    def _add_ride_stats(self, steps, k: int) -> None:
        """The stats of a ride (``steps.trajectory(k)``, :class:`~virtual_vehicle.engine.ride.RideSteps`) joined to
        those so far as :meth:`add` joins them, without making that Trajectory: kept as ``_RideJoin(base, steps, k)``,
        the join of ``base`` (None: nothing) and the ride. A ride adds nothing to the summed stats and takes its others
        from the last piece, so after a first piece that holds its kinetic energy at the start, the join of a run of
        rides is that piece's join with the last of them alone."""
        head = self.stats_pieces[0] if self.stats_pieces else None
        if head is None:
            self.stats_pieces = [_RideJoin(None, steps, k)]
            return
        if type(head) is _RideJoin:
            base = head.steps.trajectory(head.k) if head.base is None else head.base
        else:
            base = self._stats_first()[0]
        if "kinetic_start" in base.stats:
            self.stats_pieces = [_RideJoin(base, steps, k)]
        else:  # its kinetic energy at the start would be the first ride's: joined now
            self.stats_pieces = join_stats([*self._stats_first(), steps.trajectory(k)])

    def _stats_first(self) -> list:
        """``stats_pieces[:1]``, a quiet step or a join with a ride there made its Trajectory."""
        first = self.stats_pieces[:1]
        if first and type(first[0]) is tuple:
            steps, k = first[0]
            first = self.stats_pieces = [steps.trajectory(k)]
        elif first and type(first[0]) is _RideJoin:
            base, steps, k = first[0]
            ride = steps.trajectory(k)
            first = self.stats_pieces = [ride] if base is None else join_stats([base, ride])
        return first

    def to_data(self) -> dict:
        """The track as data: the samples kept (``times`` (k,) s, ``states`` (k, 6)), the events as columns
        (:meth:`Event.to_columns`), the latest ``piece`` and the ``stats_pieces`` (:meth:`Trajectory.to_data` each,
        a quiet step made its Trajectory first) and the counts."""
        self.settle()
        return {"times": np.array(self.times, dtype=np.float64), "states": _stack(self.states),
                "events": Event.to_columns(self.events),
                "piece": None if self._piece is None else self._piece.to_data(),
                "segments": int(self.segments), "rhs_evals": int(self.rhs_evals),
                "stats_pieces": [tr.to_data() for tr in self.stats_pieces]}

    @classmethod
    def from_data(cls, d, where: str = "track") -> "ParcelTrack":
        """The track :meth:`to_data` wrote; raises ValueError for data of other keys, dtypes or shapes."""
        d = fields(d, ("times", "states", "events", "piece", "segments", "rhs_evals", "stats_pieces"), where)
        track = cls()
        times = array(d, "times", "f", (None,), where)
        track.times, track.states = times.tolist(), list(array(d, "states", "f", (len(times), 6), where))
        track.events = Event.from_columns(d["events"], f"{where}.events")
        track._piece = None if d["piece"] is None else Trajectory.from_data(d["piece"], f"{where}.piece")
        track.segments, track.rhs_evals = integer(d, "segments", where), integer(d, "rhs_evals", where)
        pieces = d["stats_pieces"]
        if type(pieces) is not list or len(pieces) > 1:
            raise ValueError(f"{where}.stats_pieces: not a list of at most one piece")
        track.stats_pieces = [Trajectory.from_data(p, f"{where}.stats_pieces") for p in pieces]
        return track

    def trajectory(self) -> Trajectory:
        """The parcel's trajectory so far: the samples kept on the output grid and the latest state, the events, and
        the counts and stats added up over the ticks."""
        times, states = list(self.times), list(self.states)
        end = float(self.piece.times[-1])
        if not times or end > times[-1]:
            times.append(end)
            states.append(self.piece.states[-1].copy())
        stats = self._stats_first()[0].stats if self.stats_pieces else dict(self.piece.stats)
        return Trajectory(np.array(times), np.array(states).reshape(-1, 6), self.events, self.piece.status,
                          self.piece.t_end, self.segments, self.rhs_evals, stats)


class _RideJoin(NamedTuple):
    """A track's stats so far, kept unmade: the join (:func:`join_stats`) of ``base`` (a Trajectory; None: nothing)
    and the ride ``steps.trajectory(k)``."""

    base: Trajectory | None
    steps: object
    k: int


def join_stats(pieces: list[Trajectory]) -> list[Trajectory]:
    """The stats of consecutive pieces added up (as :func:`~virtual_vehicle.engine.plant.join` does), as one stand-in
    piece (its samples are not used)."""
    first, last = pieces[0], pieces[-1]
    return [Trajectory(first.times[:1], first.states[:1], [], last.status, last.t_end, 0, 0, joined_stats(pieces))]


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
