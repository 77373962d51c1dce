"""Distributed against central control: the same task scenario run both ways, reports side by side."""

from __future__ import annotations

from virtual_vehicle.cells.programs import PROGRAMS, program_of
from virtual_vehicle.run.sim import run


def modes(scenario) -> dict:
    """The controls :func:`compare` runs a task scenario under, by name: ``"distributed"`` and ``"central"`` (the
    scenario's program with ``central`` false and true), and every registered program that offers itself as an
    alternative for the scenario (its module's ``alternative_to(options, scenario)`` returns its options), by its
    name: ``"reserve"``, the central reservation router, for a sorting scenario without sequence numbers."""
    control = scenario.control
    out = {mode: control.model_copy(update={"central": mode == "central"}) for mode in ("distributed", "central")}
    for name, module in PROGRAMS.items():
        offer = getattr(module, "alternative_to", None)
        options = offer(control, scenario) if offer is not None else None
        if options is not None:
            out[name] = options
    return out


def compare(scenario, progress=None) -> dict:
    """Run a task scenario (a program with a task report that also runs centrally: ``"sort"`` or ``"pose"``) with
    distributed and with central control (and, for sorting, with the reservation router: see :func:`modes`), and
    return the reports side by side: {"distributed": report, "central": report[, "reserve": report]} (see the
    program module's ``report``, without the per-parcel rows), each with the run's wall time (s)."""
    task = program_of(scenario.control)
    if task.report is None or not task.CENTRAL:
        raise ValueError(f"program {scenario.control.program!r} has no task report to compare with central control")
    out = {}
    for mode, control in modes(scenario).items():
        result = run(scenario.model_copy(update={"control": control}).build(), progress)
        report = program_of(control).report(result)
        report.pop("parcels")
        report["wall_time_s"] = result.wall_time
        out[mode] = report
    return out
