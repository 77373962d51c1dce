"""Cell programs as the scenario knows them: one module per program, registered by name in :data:`PROGRAMS`.

A program module holds everything about its program that is not the policy itself (that stays in
:mod:`~virtual_vehicle.cells.control`, :mod:`~virtual_vehicle.cells.sorting`, :mod:`~virtual_vehicle.cells.tracking`):

- ``Options``: the ``[control]`` table of the scenario for it, a :class:`~.base.ProgramOptions` with
  ``program: Literal["name"]`` and only the fields it uses; validators raise plain ValueError. Its
  ``top_speed()`` is the fastest wheel speed (m/s) the program may command.
- ``build(options, ctx)``: the :class:`~.base.ControlSetup` (program, topology, delivery, per-cell configuration)
  from a :class:`~.base.BuildContext`; raises :class:`~.base.FieldError` naming the scenario field at fault.
- ``report(result)``: its task report (a dict with per-parcel rows under ``"parcels"``), or None; ``SUMMARY``: the
  run summary's block that holds it (None without a report); ``COMPARED``: (report key, label) pairs that
  ``virtual-vehicle compare`` shows; ``CENTRAL``: whether ``central = true`` runs it on one central computer;
  ``LABELS``: whether its cells read the parcels' labels (``destination``, ``sequence``).
- ``markers(setup)``: what the pictures draw for it (:class:`~.base.Markers`: entries and exits, targets).

The program's ``CellProgram`` must pass :func:`~virtual_vehicle.cells.network.programs.check_program`. A new
program is a new module and one line below; the scenario's ``[control]`` table is the union of the registered
``Options``, told apart by ``program``.
"""

from __future__ import annotations

import sys
from types import ModuleType

from virtual_vehicle.cells.programs import diffusion, pose, reserve, shuttle, sort

PROGRAMS: dict[str, ModuleType] = {
    "shuttle": shuttle,
    "pose": pose,
    "diffusion": diffusion,
    "sort": sort,
    "reserve": reserve,
}
"""The program modules by the name a scenario's ``program`` gives."""


def program_of(options) -> ModuleType:
    """The module of a program's ``options`` (the module that defines its ``Options``, so that a program registered
    in a copy of :data:`PROGRAMS` is found too)."""
    return sys.modules[type(options).__module__]


def owners(field: str, programs: dict[str, ModuleType] = PROGRAMS) -> list[str]:
    """Names of the programs whose options have ``field`` (to tell a user which program a stray field belongs to)."""
    return [name for name, module in programs.items() if field in module.Options.model_fields]


def with_task(programs: dict[str, ModuleType] = PROGRAMS, central: bool = False) -> list[str]:
    """Names of the programs with a task report (and, with ``central``, that run centrally too)."""
    return [name for name, module in programs.items() if module.report is not None and (module.CENTRAL or not central)]
