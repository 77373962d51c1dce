"""What every program module shares: the options common to all programs, what a builder is given and returns, and
what the pictures mark for a program.

Units are SI: m, s, m/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Pos = Annotated[float, Field(gt=0)]
Coord = Annotated[float, Field(ge=-1e6, le=1e6)]
"""A coordinate in m, bounded as the scenario's (|x| <= 1000 km)."""
Speed = Annotated[float, Field(ge=-1e3, le=1e3)]
"""A speed in m/s (|v| <= 1 km/s)."""
Point = tuple[Coord, Coord]
Pose = tuple[Coord, Coord, Annotated[float, Field(ge=-1e3, le=1e3)]]
"""[x, y, theta] in m, m, rad."""


class FieldError(ValueError):
    """A program's options do not fit the built scenario: ``field`` names the scenario field at fault (a TOML path,
    e.g. ``control.exits[0]``), ``message`` what is wrong; the scenario loader reports both."""

    def __init__(self, field: str, message: str):
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


class WireSpec(BaseModel):
    """Wire-level network hardware (see :class:`~virtual_vehicle.cells.network.wire.WireParams`): ``baud`` (bits/s),
    ``poll_time``, ``select_time``, ``cts_timeout``, ``backoff_max`` (s), ``max_attempts``, ``queue_limit``,
    ``bit_error_rate`` and ``loss_rate`` (0..1). Without ``cts_timeout`` a sender waits for its neighbour's answer as
    long as the longest sentence (64 bytes) holds a line at ``baud``, at least 2 ms (67 ms at 9600 baud): a neighbour
    busy with one transfer is waited for, not given up on."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    baud: Pos = 9600.0
    poll_time: Pos = 50e-6
    select_time: Annotated[float, Field(ge=0)] = 20e-6
    cts_timeout: Pos | None = None
    backoff_max: Annotated[float, Field(ge=0)] = 1e-3
    max_attempts: Annotated[int, Field(ge=1, le=1000)] = 5
    queue_limit: Annotated[int, Field(ge=1, le=1000)] = 1
    bit_error_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    loss_rate: Annotated[float, Field(ge=0, le=1)] = 0.0


class ClockSpec(BaseModel):
    """Each cell's controller on its own clock (:mod:`~virtual_vehicle.cells.network.clocks`): ``drift``, the largest
    relative rate error of a cell's crystal (0..0.1; each cell's drawn once from U(-drift, drift)), ``jitter`` (s,
    each tick late by U(0, jitter), below half the period), ``seed`` of both, and ``slots``, the instants a period
    that ticks are placed on (1..1000; cells that fall on one instant step together). The defaults (no drift, no
    jitter) are one clock shared by every cell: the synchronous run."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    drift: Annotated[float, Field(ge=0, le=0.1)] = 0.0
    jitter: Annotated[float, Field(ge=0, le=5)] = 0.0
    seed: Annotated[int, Field(ge=0)] = 0
    slots: Annotated[int, Field(ge=1, le=1000)] = 20

    @property
    def synchronous(self) -> bool:
        """Whether every cell ticks on one shared clock."""
        return self.drift == 0 and self.jitter == 0


class ProgramOptions(BaseModel):
    """Every program takes these: the cells run it each ``period`` (s); sentences travel by ``delivery``
    (``"ideal"`` rounds, or ``"wire"``: the paper's RS232 hardware, tuned by ``[control.wire]``). ``loss_rate``
    (0..1) drops sentences on ideal rounds; ``seed`` fixes the network's randomness. ``dead_links``: [cell id, port]
    pairs whose link is cut (square cells: ports 0..3 = east, north, west, south of the cell; hexagonal cells: ports
    0..5, every 60 degrees counter-clockwise from east). ``changed_only`` (default true): on ideal rounds, step a
    stationary program (the sorter) only on the cells whose sensors, sentences or state changed since the last tick
    (the others would repeat themselves); the run is the same to the last bit, false steps every cell every tick
    (:class:`~virtual_vehicle.cells.network.programs.ChangedCells`). ``[control.clock]``: the cells' own clocks
    (:class:`ClockSpec`; default: one shared clock)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    program: str
    period: Annotated[float, Field(gt=0, le=10)] = 0.01
    delivery: Literal["ideal", "wire"] = "ideal"
    loss_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    seed: Annotated[int, Field(ge=0)] = 0
    dead_links: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0, le=5)]]] = []
    wire: WireSpec = WireSpec()
    changed_only: bool = True
    clock: ClockSpec = ClockSpec()

    @model_validator(mode="after")
    def _jitter_within_period(self):
        if not self.clock.jitter < self.period / 2:
            raise ValueError(f"clock.jitter: {self.clock.jitter} s is not below half the period "
                             f"({self.period / 2:g} s)")
        return self

    @property
    def max_age(self) -> int:
        """Ticks a neighbour's sentence stays trusted: 0 on ideal rounds (every neighbour is heard every tick), 20
        on the wire, where a busy link delivers only now and then."""
        return 0 if self.delivery == "ideal" else 20


@dataclass(frozen=True)
class BuildContext:
    """What a program's builder is given, already built from the rest of the scenario: ``cells`` (the cell layer,
    :class:`~virtual_vehicle.model.layout.CellArray`), ``sensors`` (:class:`~virtual_vehicle.cells.hardware.Sensors`),
    the parcels' ``specs`` and start ``states`` (x, y, theta, vx, vy, omega in SI), the scenario's ``parcels``
    entries (their ``destination`` and ``sequence`` labels), the ``topology`` with its faults, ``make_delivery`` (a
    factory of fresh delivery models) and the map's ``marks`` (cell masks by map letter)."""

    cells: object
    sensors: object
    specs: list
    states: list
    parcels: list
    topology: object
    make_delivery: object
    marks: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ControlSetup:
    """The distributed side of a run: program, topology, a factory of fresh delivery models (each run starts from an
    idle network with its own seeded randomness), period (s), per-cell configuration, and whether a stationary
    program is stepped only on the cells that changed (where the delivery model can tell which)."""

    program: object
    topology: object
    make_delivery: object
    delivery_name: str
    period: float
    config: dict
    changed_only: bool = True
    clock: object = None
    """The cells' own clocks (:class:`~virtual_vehicle.cells.network.clocks.ClockParams`); None: one shared clock."""


def setup_for(options: ProgramOptions, ctx: BuildContext, program, config: dict | None = None) -> ControlSetup:
    """The :class:`ControlSetup` of ``program`` under ``options`` on the context's network, with per-cell
    ``config`` (what each cell is told when it is installed)."""
    from virtual_vehicle.cells.network.clocks import ClockParams

    clock = None if options.clock.synchronous else ClockParams(**options.clock.model_dump())
    if clock is not None and getattr(options, "central", False):
        raise FieldError("control.clock", "a central controller runs on one clock: own clocks (drift, jitter) are "
                                          "for the cells' programs")
    return ControlSetup(program, ctx.topology, ctx.make_delivery, options.delivery, options.period,
                        {} if config is None else config, options.changed_only, clock)


@dataclass(frozen=True)
class Markers:
    """What the pictures mark for a run of a program: ``lanes`` as (label, exit index or -1 for an entry, outline
    (k, 2) m), the parcels' ``targets`` ([x, y, theta] each, m and rad) and their ``destinations`` (exit indices,
    None for an unlabelled parcel); None where the program has none."""

    lanes: list = field(default_factory=list)
    targets: list | None = None
    destinations: list | None = None


def no_markers(setup) -> Markers:
    """Nothing to mark: a program without places or goals in the scene."""
    return Markers()

