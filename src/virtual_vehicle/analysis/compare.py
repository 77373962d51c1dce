"""Distributed against central control: the same task scenario run both ways, reports side by side."""

from __future__ import annotations

from virtual_vehicle.run.sim import run
from virtual_vehicle.run.tasks import REPORTS


def compare(scenario, progress=None) -> dict:
    """Run a task scenario (program ``"sort"`` or ``"pose"``) twice, with distributed and with central control, and
    return both reports side by side: {"distributed": report, "central": report} (see :func:`sorting_report` and
    :func:`pose_report`, without the per-parcel rows), each with the run's wall time (s)."""
    report_of = REPORTS[scenario.control.program]
    out = {}
    for mode in ("distributed", "central"):
        control = scenario.control.model_copy(update={"central": mode == "central"})
        result = run(scenario.model_copy(update={"control": control}).build(), progress)
        report = report_of(result)
        report.pop("parcels")
        report["wall_time_s"] = result.wall_time
        out[mode] = report
    return out
