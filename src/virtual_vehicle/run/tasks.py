"""Task metrics: what a run achieved, in the terms a sorting hall is judged by. Each program module in
:mod:`virtual_vehicle.cells.programs` holds its own report; here they are by name.

Units: s, m, parcels per hour.
"""

from __future__ import annotations

from virtual_vehicle.cells.programs import PROGRAMS
from virtual_vehicle.cells.programs.pose import report as pose_report
from virtual_vehicle.cells.programs.sort import report as sorting_report

__all__ = ["REPORTS", "pose_report", "sorting_report"]

REPORTS = {name: module.report for name, module in PROGRAMS.items() if module.report is not None}
"""Task reports by program: what :func:`~virtual_vehicle.analysis.compare.compare` puts side by side."""
