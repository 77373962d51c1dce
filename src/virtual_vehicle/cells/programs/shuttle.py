"""Program ``"shuttle"``: parcels passed back and forth along the wheel-0 axis (:class:`~virtual_vehicle.cells.control.
Shuttle`). Units: m/s, ticks."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from virtual_vehicle.cells.programs.base import BuildContext, ControlSetup, ProgramOptions, no_markers, setup_for


class ShuttleOptions(ProgramOptions):
    """``program = "shuttle"`` passes parcels back and forth along the wheel-0 axis at ``speed`` (m/s), reversing by
    a flood of at most ``hop_limit`` hops started by the end cells that sense a parcel; cells repeat their state
    every ``heartbeat`` ticks."""

    program: Literal["shuttle"]
    speed: Annotated[float, Field(gt=0, le=1e3)] = 0.2
    hop_limit: Annotated[int, Field(ge=1, le=254)] = 32
    heartbeat: Annotated[int, Field(ge=1, le=100_000)] = 10

    def top_speed(self) -> float:
        """The wheels' speed (m/s): the fastest the program commands."""
        return self.speed



Options = ShuttleOptions
"""The ``[control]`` table of this program."""

def build(options: ShuttleOptions, ctx: BuildContext) -> ControlSetup:
    """Every cell runs the shuttle; it needs no per-cell configuration."""
    from virtual_vehicle.cells.control import Shuttle

    return setup_for(options, ctx, Shuttle(options.speed, options.hop_limit, options.heartbeat))


SUMMARY = None
"""No task report: a shuttle has no goal to judge it by."""
report = None
COMPARED = ()
CENTRAL = False
LABELS = False
markers = no_markers
