"""Program ``"reserve"``: the central reservation router (:class:`~virtual_vehicle.cells.sorting.reserve.
ReservationRouter`), the upper bound for the Virtual Vehicle sorter on the same map, hardware and parcels: the
``[control]`` table of ``"sort"`` plus the planning ``window``; the sorter's task report and markers. Units: m, s,
m/s, parcels per hour."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Literal

from pydantic import Field, model_validator

from virtual_vehicle.cells.programs import sort
from virtual_vehicle.cells.programs.base import BuildContext, ControlSetup, FieldError


class ReserveOptions(sort.SortOptions):
    """``program = "reserve"``: one central computer routes every parcel by time-expanded reservations over the
    cell graph (:mod:`virtual_vehicle.cells.sorting.reserve`): entries, exits, ``speed`` (m/s) and ``gap`` (free
    cells kept between parcels' footprints) as for ``"sort"``; each parcel plans ``window`` steps (one step: the
    time to ride one pitch) ahead, oldest first, against the reservations of the older ones, and plans again every
    step. No sequencing (parking) and no network: ``central`` must stay false (the router is central already)."""

    program: Literal["reserve"]
    window: Annotated[int, Field(ge=2, le=200)] = 16

    @model_validator(mode="after")
    def _no_sequencing(self):
        if self.parking:
            raise ValueError("parking: the reservation router does not sequence parcels (no parking cells)")
        if self.central:
            raise ValueError("central: the reservation router is central already; leave central = false")
        return self


Options = ReserveOptions
"""The ``[control]`` table of this program."""


def build(options: ReserveOptions, ctx: BuildContext) -> ControlSetup:
    """The sorter's per-cell configuration (entries, exits and their ways out, one-way cells) with the router in
    place of the cells' program."""
    from virtual_vehicle.cells.sorting.reserve import ReservationRouter

    if any(p.sequence is not None for p in ctx.parcels):
        raise FieldError("parcels", "the reservation router does not sequence parcels: drop their sequence numbers")
    if ctx.marks.get("P") is not None and ctx.marks["P"].any():
        raise FieldError("array.map", "the reservation router does not park parcels: no P cells on the map")
    setup = sort.build(sort.SortOptions(**{k: v for k, v in options.model_dump().items() if k != "window"}
                                        | {"program": "sort", "central": True}), ctx)
    router = ReservationRouter(ctx.cells.pitch, options.speed, options.gap, options.window, period=options.period)
    return dataclasses.replace(setup, program=router, config={**setup.config, "position": ctx.cells.positions})


def alternative_to(options, scenario) -> ReserveOptions | None:
    """The router's options for running a sorting scenario (program ``"sort"``, no sequence numbers, no parking)
    on the same map, hardware and parcels, for ``virtual-vehicle compare``; None for any other scenario."""
    if (not isinstance(options, sort.SortOptions) or isinstance(options, ReserveOptions) or options.parking
            or any(p.sequence is not None for p in scenario.parcels)):
        return None
    return ReserveOptions(**(options.model_dump() | {"program": "reserve", "central": False}))


report = sort.report
SUMMARY = sort.SUMMARY
COMPARED = sort.COMPARED
CENTRAL = False
"""The router is central already: it has no central twin."""
LABELS = True
"""The cells at an entry read each parcel's label (its ``destination``)."""
markers = sort.markers
