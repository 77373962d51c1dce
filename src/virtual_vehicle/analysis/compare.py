"""Distributed against central control: the same task scenario run both ways, reports side by side."""

from __future__ import annotations

from virtual_vehicle.cells.programs import program_of
from virtual_vehicle.run.sim import run


def compare(scenario, progress=None) -> dict:
    """Run a task scenario (a program with a task report that also runs centrally: ``"sort"`` or ``"pose"``) twice,
    with distributed and with central control, and return both reports side by side: {"distributed": report,
    "central": report} (see the program module's ``report``, without the per-parcel rows), each with the run's wall
    time (s)."""
    task = program_of(scenario.control)
    if task.report is None or not task.CENTRAL:
        raise ValueError(f"program {scenario.control.program!r} has no task report to compare with central control")
    out = {}
    for mode in ("distributed", "central"):
        control = scenario.control.model_copy(update={"central": mode == "central"})
        result = run(scenario.model_copy(update={"control": control}).build(), progress)
        report = task.report(result)
        report.pop("parcels")
        report["wall_time_s"] = result.wall_time
        out[mode] = report
    return out
