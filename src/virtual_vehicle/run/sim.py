"""The Simulator: runs a validated scenario and records what happened to every parcel.

Units: SI. A constant field is run as one plant interval; a networked run advances the plant one control tick at a time.
The plant (:mod:`virtual_vehicle.engine.plant`) integrates each parcel on its own while it cannot meet another and
resolves contact between parcels when it can.

The runs themselves are in the modules below this one, and importable from here: the run loop, its checkpoints and
the constant field (:mod:`~virtual_vehicle.run.jobs`), the networked run (:mod:`~virtual_vehicle.run.network`), the
cells on their own clocks (:mod:`~virtual_vehicle.run.clocked`), the parcels' tracks
(:mod:`~virtual_vehicle.run.tracks`) and what a run produced (:mod:`~virtual_vehicle.run.results`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from virtual_vehicle.config.scenario import Setup
from virtual_vehicle.errors import VirtualVehicleError
from virtual_vehicle.run.clocked import ClockedRun
from virtual_vehicle.run.jobs import FieldRun, _load, carry_on, run_kind
from virtual_vehicle.run.network import NetworkRun, TickedRun, wheel_loads
from virtual_vehicle.run.results import (CellLog, LatencyStats, NetworkRecord, ParcelResult, RunResult,
                                         coulomb_sliding_check, plant_totals)
from virtual_vehicle.run.tracks import ParcelTrack, join_stats

__all__ = ["run", "run_network", "resume", "carry_on", "network_job", "run_kind", "FieldRun", "TickedRun",
           "NetworkRun", "ClockedRun", "ParcelTrack", "join_stats", "ParcelResult", "CellLog", "RunResult",
           "NetworkRecord", "LatencyStats", "coulomb_sliding_check", "plant_totals", "wheel_loads"]

_KINDS = {"field": FieldRun, "network": NetworkRun, "clocked": ClockedRun}
"""The runs by kind, as a checkpoint names it (:attr:`~virtual_vehicle.run.jobs._Job.KIND`)."""


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
    job, every = _load(data, _KINDS, where=str(path))
    return job.run(progress, checkpoint=path, checkpoint_every=checkpoint_every or every)


def network_job(setup: Setup) -> "NetworkRun":
    """The run of a networked scenario: its cells on one shared clock (:class:`NetworkRun`) or each on its own
    (:class:`ClockedRun`, a scenario with ``[control.clock]`` drift or jitter)."""
    return NetworkRun(setup) if setup.control.clock is None else ClockedRun(setup)
