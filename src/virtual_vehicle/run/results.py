"""What a run produced: every parcel's trajectory and the paper's Coulomb check on it (:class:`ParcelResult`), the
network's traffic (:class:`NetworkRecord`, :class:`LatencyStats`), every cell at every tick (:class:`CellLog`) and the
whole, with its JSON-ready summary (:class:`RunResult`).

Units: SI (s, m, m/s, J).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from virtual_vehicle import __version__
from virtual_vehicle.cells.network.topology import Topology
from virtual_vehicle.cells.programs import program_of
from virtual_vehicle.config.scenario import Setup
from virtual_vehicle.engine.dynamics import Trajectory
from virtual_vehicle.model.parcel import ParcelSpec, supporting_cells
from virtual_vehicle.model.state_data import array, fields, integer, number

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
