"""The Simulator: runs a validated scenario and records what happened to every parcel.

Units: SI. For this release the wheel velocities are constant over a run (the paper's Section 4 assumption) and
parcels do not touch each other, so each parcel is integrated on its own over the whole duration.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import __version__
from .dynamics import ParcelModel, Trajectory, integrate
from .friction import CoulombLaw
from .parcel import ParcelSpec, supporting_cells
from .scenario import Setup


@dataclass
class ParcelResult:
    """One parcel's run. ``sliding_violation`` is, for the Coulomb law, the first sample time (s) at which some
    supporting wheel no longer slid under the parcel in its direction of spin (the paper's Coulomb assumption), and
    the largest reversed slip (m/s) seen; None when the assumption held at every sample."""

    spec: ParcelSpec
    trajectory: Trajectory
    sliding_violation: tuple[float, float] | None = None


@dataclass
class RunResult:
    """Everything a run produced."""

    setup: Setup
    parcels: list[ParcelResult]
    wall_time: float
    stats: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """A JSON-ready summary: per-parcel outcome, start/end state, distance, events; run totals."""
        sc = self.setup.scenario
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
                "segments": tr.segments,
                "rhs_evaluations": tr.rhs_evals,
                "coulomb_sliding_assumption_violated_at_s": pr.sliding_violation[0] if pr.sliding_violation else None,
                "coulomb_max_reversed_slip_m_per_s": pr.sliding_violation[1] if pr.sliding_violation else None,
            })
        simulated = sum(pr.trajectory.t_end for pr in self.parcels)
        return {
            "scenario": sc.name,
            "version": __version__,
            "friction_law": sc.friction.law,
            "integrator": sc.integrator.mode,
            "duration_s": sc.duration,
            "cells": self.setup.cells.n,
            "parcels": parcels,
            "wall_time_s": self.wall_time,
            "real_time_factor": (sc.duration / self.wall_time) if self.wall_time > 0 else None,
            "parcel_seconds_simulated": simulated,
            **self.stats,
        }


def coulomb_sliding_check(setup: Setup, spec: ParcelSpec, traj: Trajectory) -> tuple[float, float] | None:
    """Check the paper's Coulomb assumption at every sample: under each supporting cell, each spinning wheel's
    surface speed along its drive direction exceeds the parcel's (so the wheel slides in its direction of spin).
    Returns (first violating time s, largest reversed slip m/s) or None."""
    cells = setup.cells
    first, worst = None, 0.0
    for t, y in zip(traj.times, traj.states):
        ids = supporting_cells(spec, y, cells.positions, cells.tree)
        if len(ids) == 0:
            continue
        r = cells.positions[ids] - y[:2]
        w = y[3:5] + y[5] * np.column_stack([-r[:, 1], r[:, 0]])  # parcel velocity over each cell
        U = cells.drive_directions[ids]
        wheel = np.einsum("ij,ikj->ik", setup.velocities[ids], U)
        parcel = np.einsum("ij,ikj->ik", w, U)
        reversed_slip = np.where(wheel != 0, -np.sign(wheel) * (wheel - parcel), -np.inf)
        m = float(reversed_slip.max())
        if m > 1e-9:
            first = float(t) if first is None else first
            worst = max(worst, m)
    return None if first is None else (first, worst)


def run(setup: Setup, progress: Callable[[float], None] | None = None) -> RunResult:
    """Run a built scenario. ``progress`` is called with the fraction of the run done (0..1)."""
    sc = setup.scenario
    integ = sc.integrator
    t_end = sc.duration
    sample_dt = sc.output_dt or t_end / 500
    start = time.perf_counter()
    results = []
    n = len(setup.specs)
    for i, (spec, y0) in enumerate(zip(setup.specs, setup.states)):
        model = ParcelModel(setup.cells, spec, setup.velocities, setup.law, sc.gravity)
        report = None if progress is None else (lambda t, i=i: progress((i + t / t_end) / n))
        traj = integrate(model, y0, 0.0, t_end, mode=integ.mode, rtol=integ.rtol, atol=integ.atol,
                         max_step=integ.max_step or np.inf, dt=integ.dt, sample_dt=sample_dt, progress=report)
        check = coulomb_sliding_check(setup, spec, traj) if isinstance(setup.law, CoulombLaw) else None
        results.append(ParcelResult(spec, traj, check))
    if progress is not None:
        progress(1.0)
    return RunResult(setup, results, time.perf_counter() - start)
