"""Scenario files (TOML), validated: every field checked for type, unit range and cross-field rules.

Units are SI throughout: m, s, kg, kg m^2, rad, m/s, rad/s, m/s^2. A bundled scenario can be named instead of a
path (see :func:`bundled_scenarios`). Errors are :class:`~virtual_vehicle.errors.ScenarioError` naming the field.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
import shapely
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from virtual_vehicle.cells.programs import PROGRAMS, owners, program_of
from virtual_vehicle.cells.programs.base import BuildContext, ControlSetup, FieldError, WireSpec
from virtual_vehicle.errors import ScenarioError, TippingError
from virtual_vehicle.model import fields as fieldlib
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import ParcelSpec, polygon, rectangle, supporting_cells
from virtual_vehicle.physics.laws import LAWS, FrictionLaw

Pos = Annotated[float, Field(gt=0)]
Coord = Annotated[float, Field(ge=-1e6, le=1e6)]
"""A coordinate in m: the simulator's geometry is meant for floors, not for astronomy (|x| <= 1000 km)."""
Length = Annotated[float, Field(ge=1e-9, le=1e3)]
"""A size in m (a pitch, a parcel's side): from a nanometre (well below the smallest micro-actuator arrays, whose
pitch is ~0.1 mm) to a kilometre. Below ~1e-9 m forces, inertias and tolerances underflow in the solvers."""
Mass = Annotated[float, Field(ge=1e-12, le=1e7)]
"""A parcel's mass in kg: from a nanogram (a micro-part on a MEMS array, with three decades to spare) to 10 000 t
(box cars on truck tyres, paper Section 1). Below ~1e-12 kg the products of mass, inertia and friction underflow
(``mass = 1e-300`` divided by zero)."""
Speed = Annotated[float, Field(ge=-1e3, le=1e3)]
"""A speed in m/s (|v| <= 1 km/s)."""
Point = tuple[Coord, Coord]
Vel = tuple[Speed, Speed]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


@contextlib.contextmanager
def _at(path: str):
    """Name the TOML ``path`` a library call was built from: the model, cells and hardware raise plain ValueError
    (they know nothing of scenario files), which becomes a ScenarioError naming the field here. A ScenarioError
    raised inside (already naming its field) passes unchanged."""
    try:
        yield
    except ScenarioError:
        raise
    except ValueError as exc:
        raise ScenarioError(path, str(exc)) from None


class BeltSpec(_Strict):
    """A plain conveyor belt beside the array (:func:`~virtual_vehicle.model.layout.with_belts`): centreline from
    ``start`` to ``end`` (m), ``width`` (m), surface ``speed`` (m/s, from start to end; it never changes: a plain
    belt has no controller and sends no sentences), support points ``spacing`` (m, default half the pitch) apart.
    A dead belt (its cell id comes after the array's cells, in order) stands still."""

    start: Point
    end: Point
    width: Annotated[float, Field(gt=0, le=1e3)]
    speed: Speed
    spacing: Annotated[float, Field(gt=0, le=1e3)] | None = None


class _ArrayBase(_Strict):
    belts: list[BeltSpec] = []


class _Wheels(_ArrayBase):
    wheels: Literal["lumped", "separate"] = "lumped"
    wheel_offsets: tuple[Point, Point] | None = None


class _Lattice(_Wheels):
    pitch: Length
    origin: Point = (0.0, 0.0)
    drive_angle: Annotated[float, Field(ge=-1e3, le=1e3)] = 0.0


class GridArray(_Lattice):
    """``nx`` columns by ``ny`` rows at ``pitch`` (m), first cell at ``origin`` (m); wheel 0 drives along
    ``drive_angle`` (rad from +x), wheel 1 at +90 degrees. Every array takes ``wheels = "lumped"`` (the paper: both
    wheels at the cell centre, default) or ``"separate"`` (each wheel its own contact at ``wheel_offsets``, m in the
    cell frame, default wheel 0 at (0, -pitch/4) and wheel 1 at (-pitch/4, 0); coulomb and stick_slip laws, ideal
    wheels). Every array may also list ``belts`` ([[array.belts]] tables, :class:`BeltSpec`): plain conveyor belts
    beside it, feeding parcels in or taking them away."""

    kind: Literal["grid"]
    nx: Annotated[int, Field(ge=1, le=100_000)]
    ny: Annotated[int, Field(ge=1, le=100_000)]


class RowArray(_Lattice):
    """A single row of ``n`` cells along +x (the paper's 1-D array), spaced and oriented as a grid: ``pitch`` (m),
    ``origin`` (m), ``drive_angle`` (rad), ``wheels``, ``wheel_offsets`` (m) and ``belts`` as for :class:`GridArray`."""

    kind: Literal["row"]
    n: Annotated[int, Field(ge=1, le=1_000_000)]


class PointsArray(_Wheels):
    """Cells at explicit ``points`` (m); ``pitch`` (m) defaults to the median nearest-neighbour distance;
    ``drive_angle`` (rad), ``wheels``, ``wheel_offsets`` (m) and ``belts`` as for :class:`GridArray`."""

    kind: Literal["points"]
    points: Annotated[list[Point], Field(min_length=1)]
    pitch: Length | None = None
    drive_angle: Annotated[float, Field(ge=-1e3, le=1e3)] = 0.0


class UniformField(_Strict):
    """Every cell at ``velocity`` (m/s)."""

    kind: Literal["uniform"]
    velocity: Vel


class InwardField(_Strict):
    """Each wheel spins toward ``center`` (m) at ``speed`` (m/s) (the paper's 2x2 inward field)."""

    kind: Literal["inward"]
    center: Point
    speed: Annotated[float, Field(gt=0, le=1e3)]


class ReversedEndField(_Strict):
    """All cells at ``velocity`` (m/s) except the far end along it, reversed (the 1-D oscillator)."""

    kind: Literal["reversed_end"]
    velocity: Vel


class PerCellField(_Strict):
    """Explicit ``velocities`` (m/s), one [vx, vy] per cell in the array's order."""

    kind: Literal["per_cell"]
    velocities: list[Vel]


class RadialField(_Strict):
    """Every cell drives straight toward ``center`` (m) at ``speed`` (m/s; negative: away)."""

    kind: Literal["radial"]
    center: Point
    speed: Speed


class SqueezeField(_Strict):
    """Cells drive toward the line through ``point`` (m) along ``direction`` at ``speed`` (m/s), and along it at
    ``along`` (m/s)."""

    kind: Literal["squeeze"]
    point: Point
    direction: Point
    speed: Speed
    along: Speed = 0.0


class RotationField(_Strict):
    """Rigid rotation at ``omega`` (rad/s, counter-clockwise) about ``center`` (m)."""

    kind: Literal["rotation"]
    center: Point
    omega: Annotated[float, Field(ge=-1e4, le=1e4)]


class TwistField(_Strict):
    """The rigid-body velocity of twist ``twist`` = [vx, vy (m/s), omega (rad/s)] about ``center`` (m)."""

    kind: Literal["twist"]
    center: Point
    twist: tuple[Speed, Speed, Annotated[float, Field(ge=-1e4, le=1e4)]]


BaseFieldSpec = Annotated[Union[UniformField, InwardField, ReversedEndField, PerCellField, RadialField, SqueezeField,
                                RotationField, TwistField], Field(discriminator="kind")]


class Region(_Strict):
    """Cells inside ``outline`` ([[x, y], ...] m) follow ``field``."""

    outline: Annotated[list[Point], Field(min_length=3, max_length=10_000)]
    field: BaseFieldSpec


class RegionsField(_Strict):
    """Fields composed by region: the first of ``regions`` whose outline contains a cell drives it; other cells
    follow ``default`` (stopped when absent)."""

    kind: Literal["regions"]
    regions: Annotated[list[Region], Field(min_length=1)]
    default: BaseFieldSpec | None = None


class HexArray(_ArrayBase):
    """A hexagonal lattice (:func:`~virtual_vehicle.model.layout.hexagonal`): ``ny`` rows of ``nx`` cells whose
    neighbours are ``pitch`` (m) apart, odd rows shifted by half a pitch, first cell at ``origin`` (m), six network
    ports a cell. Every cell drives three omni wheels at 120 degrees
    (:func:`~virtual_vehicle.model.layout.three_wheels`),
    ``wheel_radius`` (m, default pitch/4) from its centre, wheel 0 along ``drive_angle`` (rad); coulomb and
    stick_slip laws, ideal wheels, whole-cell faults only. ``belts`` as for :class:`GridArray`."""

    kind: Literal["hex"]
    nx: Annotated[int, Field(ge=1, le=100_000)]
    ny: Annotated[int, Field(ge=1, le=100_000)]
    pitch: Length
    origin: Point = (0.0, 0.0)
    drive_angle: Annotated[float, Field(ge=-1e3, le=1e3)] = 0.0
    wheel_radius: Pos | None = None


class MapArray(_Lattice):
    """Cells drawn as text (:func:`~virtual_vehicle.model.layout.from_map`): ``map`` has one character per lattice site,
    the last line at ``origin`` (m), lines above it higher in y, ``pitch`` (m) apart, wheel 0 of every cell along
    ``drive_angle`` (rad); ``o`` or ``#`` is a cell,
    ``E`` an entry cell, ``0``..``3`` a cell of that exit (program ``"sort"`` takes its entries and exits from
    these when ``[control]`` names none), space or ``.`` no cell. ``lattice`` is ``"square"`` (four ports a cell;
    ``wheels`` and ``wheel_offsets`` as for :class:`GridArray`) or ``"hex"`` (six ports, three omni wheels
    ``wheel_radius`` m from the centre, as for :class:`HexArray`). ``belts`` as for :class:`GridArray`."""

    kind: Literal["map"]
    map: Annotated[str, Field(min_length=1, max_length=10_000_000)]
    lattice: Literal["square", "hex"] = "square"
    wheel_radius: Pos | None = None

    @model_validator(mode="after")
    def _wheels_fit_lattice(self):
        if self.lattice == "hex" and (self.wheels != "lumped" or self.wheel_offsets is not None):
            raise ValueError("hexagonal cells have three omni wheels (set wheel_radius); wheels and wheel_offsets "
                             "are for square cells")
        if self.lattice == "square" and self.wheel_radius is not None:
            raise ValueError("wheel_radius is for hexagonal cells (lattice = \"hex\")")
        return self


PartSpec = Annotated[Union[GridArray, RowArray, PointsArray, HexArray, MapArray], Field(discriminator="kind")]


class MixedArray(_ArrayBase):
    """Several arrays joined into one (:func:`~virtual_vehicle.model.layout.combine`): ``parts`` is a list of array
    tables of any other kind (square grids, rows, points, hexagonal lattices, maps) with one pitch; cells are numbered
    part after part and each keeps its wheels and ports, so square and hexagonal cells that meet talk across the seam.
    ``belts`` as for :class:`GridArray` (on the whole array, not on its parts)."""

    kind: Literal["mixed"]
    parts: Annotated[list[PartSpec], Field(min_length=1, max_length=1000)]

    @model_validator(mode="after")
    def _belts_on_the_whole(self):
        if any(part.belts for part in self.parts):
            raise ValueError("belts go on the mixed array itself ([[array.belts]]), not on its parts")
        return self


ArraySpec = Annotated[Union[GridArray, RowArray, PointsArray, HexArray, MapArray, MixedArray],
                      Field(discriminator="kind")]
FieldSpec = Annotated[Union[UniformField, InwardField, ReversedEndField, PerCellField, RadialField, SqueezeField,
                            RotationField, TwistField, RegionsField], Field(discriminator="kind")]


class FrictionSpec(_Strict):
    """``law``: ``"stick_slip"`` (the default; paper Section 5: wheels stick or slide, parcel ``mu`` kinetic and
    ``mu_static`` static, dimensionless; exact, event by event, in event mode; time-stepped at ``integrator.dt`` in
    fixed mode and where parcels push each other), ``"coulomb"`` (paper 4.3; parcel ``mu`` dimensionless) or
    ``"viscous"`` (paper 4.4; ``mu`` in s/m). Stick-slip is the default because it is what a real array does: the
    paper's Coulomb law assumes every wheel slides under the parcel, so a parcel that catches up with its wheels
    runs away, and the viscous law lags the wheels for ever; both stay, named, for the paper's analyses."""

    law: Literal[tuple(LAWS)] = "stick_slip"  # the registered laws


class IntegratorSpec(_Strict):
    """``mode``: ``"event"`` (piecewise, support changes located; default) or ``"fixed"`` (RK4 at step ``dt``, s).
    ``rtol``/``atol`` (state units) and ``max_step`` (s) tune the event-driven integrator. ``batch`` (default true): in
    event mode without ``max_step``, control ticks proven free of support changes are stepped for all parcels at once
    (the event engine's own single DOP853 step, in one compiled call; see :mod:`virtual_vehicle.engine.batch`), and
    under the stick-slip law those in which a parcel rides its wheels rigidly take the rigid motion in closed form
    (:mod:`virtual_vehicle.engine.ride`), and those translating over one uniform field take their catch-ups and
    support events in closed form (:mod:`virtual_vehicle.engine.glide`); false integrates every parcel on its own.
    Where support changes chatter (a sliding mode: a parcel held on a boundary
    between support sets whose pieces each push it into the other), event mode crosses that boundary in fixed RK4 steps
    of ``dt`` and counts them as the parcel's ``chatter_steps``.

    ``dt`` must resolve the scene: at most ``pitch / (10 v_max)``, a tenth of a cell at the fastest speed known
    before the run (wheels and belts of a constant field, the program's ``speed``, the diffusion ``sources``, the
    parcels' starting speeds); with ``mode = "fixed"`` also at most ``output_dt`` (when given)
    and the duration. A coarser step would jump over support changes and evaluate the parcel where it never was."""

    mode: Literal["event", "fixed"] = "event"
    rtol: Annotated[float, Field(gt=0, lt=1)] = 1e-10
    atol: Pos = 1e-12
    max_step: Pos | None = None
    dt: Pos = 1e-3
    batch: bool = True


class ContactSpec(_Strict):
    """How parcels touch each other (see :class:`~virtual_vehicle.physics.collide.ContactParams`): ``mu`` side-to-side
    Coulomb friction (dimensionless), ``margin`` (m) gap within which a contact is considered, ``slop`` (m) overlap
    tolerated before it is pushed back, ``window`` (s) longest plant window while parcels could meet,
    ``min_window`` (s): parcels that could meet within it are stepped together at ``integrator.dt``. Contacts are
    inelastic (no bounce)."""

    mu: Annotated[float, Field(ge=0, le=10)] = 0.3
    margin: Annotated[float, Field(gt=0, le=1)] = 1e-3
    slop: Annotated[float, Field(ge=0, le=0.1)] = 1e-4
    window: Annotated[float, Field(gt=0, le=1e4)] = 1.0
    min_window: Annotated[float, Field(gt=0, le=100)] = 0.02

    def params(self):
        """These settings as the plant's :class:`~virtual_vehicle.physics.collide.ContactParams`."""
        from virtual_vehicle.physics.collide import ContactParams

        return ContactParams(mu=self.mu, margin=self.margin, slop=self.slop, window=self.window,
                             min_window=self.min_window)


def control_spec(programs: dict = PROGRAMS):
    """The ``[control]`` table's type for a registry of program modules (name -> module): the union of their
    ``Options``, told apart by ``program``. :data:`ControlSpec` is that of :data:`PROGRAMS`."""
    options = tuple(m.Options for m in programs.values())
    return Annotated[Union[options], Field(discriminator="program")] if len(options) > 1 else options[0]


ControlSpec = control_spec()
"""Distributed control (the ``[control]`` table): every cell runs ``program``, a name in
:data:`~virtual_vehicle.cells.programs.PROGRAMS`; each takes the shared options of
:class:`~virtual_vehicle.cells.programs.base.ProgramOptions` and its own (its module's ``Options``)."""


class SensorSpec(_Strict):
    """Presence sensors of every cell: ``offsets`` (1..5 [x, y] in m in the cell's frame; default centre and the four
    edge midpoints), flip probabilities ``false_positive`` / ``false_negative``, faults ``stuck_on`` / ``stuck_off``
    as [cell id, sensor index] pairs, ``seed`` of the noise, and ``record`` = true to write every tick's readings
    and wheel speeds (the ``cells`` table, networked runs)."""

    offsets: Annotated[list[Point], Field(min_length=1, max_length=5)] | None = None
    false_positive: Annotated[float, Field(ge=0, le=1)] = 0.0
    false_negative: Annotated[float, Field(ge=0, le=1)] = 0.0
    stuck_on: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]]] = []
    stuck_off: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]]] = []
    seed: Annotated[int, Field(ge=0)] = 0
    record: bool = False


class WheelSpec(_Strict):
    """How the wheels follow their commands: ``model = "ideal"`` (actual speed = commanded) or ``"motor"`` (a DC
    gearmotor per wheel with PWM limit, encoder and PI loop; see :class:`~virtual_vehicle.cells.hardware.MotorParams`
    for the parameters below, SI units). With a constant ``[field]``, motors are commanded every ``period`` (s); with
    ``[control]`` its period is used.

    Motor parameters: ``supply_voltage`` (V, the H-bridge's limit); ``resistance`` (ohm), ``torque_constant``
    (N m/A, also the back-EMF constant in V s/rad), ``rotor_inertia`` (kg m^2) and ``viscous_damping`` (N m s/rad)
    on the motor side; ``gear_ratio`` (motor turns per wheel turn); ``wheel_radius`` (m) and ``wheel_inertia``
    (kg m^2) on the wheel side; ``encoder_counts`` per motor revolution; ``kp`` (V per m/s) and ``ki`` (V per m) of
    the PI loop on surface speed.

    ``profile``: a named set of these settings (:data:`~virtual_vehicle.cells.hardware.PROFILES`; ``"industrial"``:
    wheels to 1.1 m/s, 2.5 m/s^2, about 150 ms response) that implies ``model = "motor"`` and fills every motor
    parameter the table does not give; ``"custom"`` (default) uses the table as it is."""

    profile: Literal["custom", "industrial"] = "custom"
    model: Literal["ideal", "motor"] = "ideal"
    period: Annotated[float, Field(gt=0, le=10)] = 0.01
    supply_voltage: Pos = 12.0
    resistance: Pos = 2.0
    torque_constant: Pos = 0.02
    rotor_inertia: Pos = 2e-6
    viscous_damping: Annotated[float, Field(ge=0)] = 1e-6
    gear_ratio: Pos = 30.0
    wheel_radius: Pos = 0.02
    wheel_inertia: Pos = 2e-5
    encoder_counts: Annotated[int, Field(ge=1)] = 512
    kp: Annotated[float, Field(ge=0)] = 20.0
    ki: Annotated[float, Field(ge=0)] = 1500.0

    @model_validator(mode="before")
    @classmethod
    def _fill_from_profile(cls, data):
        """A named profile sets the motor model and every parameter the table leaves out."""
        from virtual_vehicle.cells.hardware import PROFILES

        if isinstance(data, dict) and data.get("profile") in PROFILES:
            data = {"model": "motor", **PROFILES[data["profile"]], **data}
        return data

    def motor(self):
        """These settings as :class:`~virtual_vehicle.cells.hardware.MotorParams` (SI units)."""
        from virtual_vehicle.cells.hardware import MotorParams

        return MotorParams(**self.model_dump(exclude={"profile", "model", "period"}))


class FaultEvent(_Strict):
    """Faults that appear at time ``t`` (s) of a networked run and stay: ``dead_cells``, ``stuck_wheels``,
    ``dead_links`` ([cell id, port]) and stuck sensors ``stuck_on`` / ``stuck_off`` ([cell id, sensor index]);
    ``revived_cells``: dead cells repaired then (they drive, sense and talk again; a cell cannot be in both lists)."""

    t: Annotated[float, Field(gt=0, le=1e7)]
    dead_cells: list[Annotated[int, Field(ge=0)]] = []
    stuck_wheels: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0, le=1)]]] = []
    dead_links: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0, le=5)]]] = []
    stuck_on: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]]] = []
    stuck_off: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0)]]] = []
    revived_cells: list[Annotated[int, Field(ge=0)]] = []


class FaultSpec(_Strict):
    """Broken hardware (:mod:`virtual_vehicle.model.faults`): listed ``dead_cells`` (cell ids: no drive, no sentences),
    ``stuck_wheels`` and ``free_wheels`` ([cell id, wheel 0 or 1] pairs: held still / spinning freely, no traction
    along its drive; free wheels need the coulomb or stick_slip law), and faults drawn at random, each item
    independently with probability ``dead_cell_rate``, ``stuck_wheel_rate``, ``free_wheel_rate``,
    ``dead_link_rate`` (per link) and ``stuck_sensor_rate`` (per sensor; stuck on or off with equal chance), from
    ``seed``. Dead links can also be listed as ``[control] dead_links``; stuck sensors as ``[sensors] stuck_on`` /
    ``stuck_off``. ``events`` ([[faults.events]] tables, :class:`FaultEvent`) inject faults at given times of a
    networked run (either delivery model: under the wire model a dying cell loses its queued sentences and
    transfers in progress over a cut link are broken off). ``dead_wheels``: what a dead cell's wheels do, ``"held"``
    (still, as a gear train that cannot be driven backwards: they hold a parcel with up to its static friction) or
    ``"free"`` (they turn with the parcel, as a back-drivable train or a released clutch: the cell carries weight and
    gives no traction; coulomb or stick_slip law, two-wheel cells, cells dead from the start to the end: with events
    that kill or revive cells it is an error)."""

    dead_cells: list[Annotated[int, Field(ge=0)]] = []
    stuck_wheels: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0, le=1)]]] = []
    free_wheels: list[tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=0, le=1)]]] = []
    dead_cell_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    stuck_wheel_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    free_wheel_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    dead_link_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    stuck_sensor_rate: Annotated[float, Field(ge=0, le=1)] = 0.0
    seed: Annotated[int, Field(ge=0)] = 0
    dead_wheels: Literal["held", "free"] = "held"
    events: list[FaultEvent] = []


class CellChange(_Strict):
    """At time ``t`` (s) of a networked run, the cells ``remove`` (ids) are taken out of the array and the cells
    ``add`` (ids of cells absent until then) are snapped in."""

    t: Annotated[float, Field(gt=0, le=1e7)]
    remove: list[Annotated[int, Field(ge=0)]] = []
    add: list[Annotated[int, Field(ge=0)]] = []


class ReconfigurationSpec(_Strict):
    """Cells taken out of the array and put in while a networked run goes on (paper Section 1: modularity and
    reconfiguration). ``absent``: cell ids of the array with no cell installed at the start (the array lists every
    site a cell may ever occupy); ``changes`` ([[reconfiguration.changes]] tables, :class:`CellChange`) remove
    and add cells at given times. An absent cell carries nothing, drives nothing, senses nothing and has no links;
    a cell snapped in starts its program from scratch (as a new cell would) and its neighbours' programs
    re-converge. Distributed programs (either delivery model) and ideal wheels; belts stay where they are."""

    absent: list[Annotated[int, Field(ge=0)]] = []
    changes: list[CellChange] = []


class ParcelEntry(_Strict):
    """A parcel, called ``name`` (unique in the scenario): either a rectangle, ``length`` along its body x and ``width``
    (m), or any simple outline ``vertices`` ([[x, y], ...] m, convex or not) with optional centre of mass ``com`` (m,
    same frame; default the centroid); ``mass`` (kg), ``mu`` (friction coefficient, see :class:`FrictionSpec`), optional
    ``mu_static`` (stick-slip), optional ``inertia`` (kg m^2, default uniform plate), and its initial state: centre of
    mass ``x``, ``y`` (m), heading ``theta`` (rad), ``vx``, ``vy`` (m/s), ``omega`` (rad/s). ``t_start`` (s): when the
    parcel is put on the array (networked runs; it waits while its place is taken); ``destination``: the exit (0..3) its
    label names, read by the cells at an entry (program ``"sort"``); ``sequence``: its place in the order in which
    parcels must leave (0, 1, 2, ... over the parcels that have one: a parcel whose number is not yet due waits on a
    parking cell)."""

    name: Annotated[str, Field(min_length=1, max_length=64)]
    length: Length | None = None
    width: Length | None = None
    vertices: Annotated[list[Point], Field(min_length=3, max_length=1000)] | None = None
    com: Point | None = None
    mass: Mass
    mu: Annotated[float, Field(gt=0, le=1e6)]
    mu_static: Annotated[float, Field(gt=0, le=1e6)] | None = None
    inertia: Annotated[float, Field(ge=1e-30, le=1e15)] | None = None  # kg m^2: a nanogram a nanometre across
    x: Coord
    y: Coord
    theta: Annotated[float, Field(ge=-1e6, le=1e6)] = 0.0
    vx: Speed = 0.0
    vy: Speed = 0.0
    omega: Annotated[float, Field(ge=-1e4, le=1e4)] = 0.0
    t_start: Annotated[float, Field(ge=0, le=1e7)] = 0.0
    destination: Annotated[int, Field(ge=0, le=3)] | None = None
    sequence: Annotated[int, Field(ge=0, le=8000)] | None = None

    @model_validator(mode="after")
    def _one_shape(self):
        rect = self.length is not None or self.width is not None
        if rect == (self.vertices is not None):
            raise ValueError("give either length and width (a rectangle) or vertices (any outline)")
        if rect and (self.length is None or self.width is None):
            raise ValueError("a rectangle needs both length and width")
        if self.com is not None and self.vertices is None:
            raise ValueError("com goes with vertices (a rectangle's centre of mass is its centre)")
        return self


class Scenario(_Strict):
    """A whole run: the array, the wheel-velocity field, the friction law, the parcels and how long to simulate.

    ``name`` and ``description`` label it (the name names its results); ``duration`` (s) is the simulated time;
    ``output_dt`` (s) the spacing of trajectory samples (default duration/500); ``gravity`` in m/s^2. The tables:
    ``array`` (the cells), either ``field`` (constant wheel velocities) or ``control`` (the cells run a program
    over a network), ``friction``, ``integrator``, ``contacts`` (parcel against parcel), ``sensors``, ``wheels``
    (ideal or motor-driven), ``faults`` (broken hardware), ``reconfiguration`` (cells taken out and put in during
    a run) and one ``parcels`` entry per parcel. ``arrivals``: ``"scheduled"`` puts each parcel on at its ``t_start``
    (once its place is free); ``"saturate"`` (networked runs) feeds every entry as fast as it accepts: every parcel
    waits at its place from the start, each place (entry) with its own queue in file order, and the next is put on
    as soon as the one before it has made room (``t_start`` is not read), to measure saturation throughput.

    Before a run starts, what it will hold in memory (output samples times parcels, networked runs' per-tick
    records, recorded cells, fixed steps) is estimated; a scenario needing more than half the machine's memory is
    refused, naming the field that drives it (e.g. ``output_dt``).
    """

    name: Annotated[str, Field(min_length=1)] = "scenario"
    description: str = ""
    duration: Annotated[float, Field(gt=0, le=1e7)]
    output_dt: Pos | None = None
    gravity: Pos = 9.81
    array: ArraySpec
    field: FieldSpec | None = None
    control: ControlSpec | None = None
    friction: FrictionSpec = FrictionSpec()
    integrator: IntegratorSpec = IntegratorSpec()
    contacts: ContactSpec = ContactSpec()
    sensors: SensorSpec = SensorSpec()
    wheels: WheelSpec = WheelSpec()
    faults: FaultSpec = FaultSpec()
    reconfiguration: ReconfigurationSpec = ReconfigurationSpec()
    arrivals: Literal["scheduled", "saturate"] = "scheduled"
    parcels: Annotated[list[ParcelEntry], Field(min_length=1)]

    @model_validator(mode="after")
    def _cross_field_rules(self):
        seen = set()
        for p in self.parcels:
            if p.name in seen:
                raise ValueError(f"parcel name {p.name!r} is used twice; names must be unique")
            seen.add(p.name)
        if (self.field is None) == (self.control is None):
            raise ValueError("give either [field] (constant wheel velocities) or [control] (cells run a program), "
                             "not both or neither")
        if self.output_dt is not None and self.output_dt > self.duration:
            raise ValueError(f"output_dt ({self.output_dt} s) is longer than duration ({self.duration} s)")
        if self.contacts.slop >= self.contacts.margin:
            raise ValueError(f"contacts.slop ({self.contacts.slop} m) must be below contacts.margin "
                             f"({self.contacts.margin} m)")
        return self

    def build(self) -> "Setup":
        """Build the simulation objects and check the rules that need them (cells, parcels on the array, no
        overlaps). Raises ScenarioError naming the field."""
        from virtual_vehicle.cells.network.topology import from_layout
        from virtual_vehicle.model.faults import later, resolve

        cells, contacts, marks = _build_array(self.array)
        with _at("field"):
            velocities = np.zeros((cells.n, 2)) if self.field is None else _build_field(self.field).velocities(cells)
        if cells.belts.any():  # plain belts run at their own speed whatever the field says
            dirs = cells.drive_directions
            velocities = np.einsum("ik,ikj->ij", cells.belt_commands(np.einsum("ij,ikj->ik", velocities, dirs)), dirs)
        sensors = _build_sensors(self.sensors, cells)
        listed_links = self.control.dead_links if self.control is not None else ()
        for k, (cell, port) in enumerate(listed_links):
            if cell >= cells.n:
                raise ScenarioError(f"control.dead_links[{k}]", f"cell {cell} does not exist (the array has {cells.n})")
            if port >= cells.ports[cell]:
                raise ScenarioError(f"control.dead_links[{k}]", f"cell {cell} has ports 0..{cells.ports[cell] - 1}")
        _check_listed_faults(self.faults, cells.n, sensors.count, "faults")
        with _at("faults"):
            faults = resolve(self.faults, cells, sensors.count, from_layout(cells).neighbor, listed_links)
        law = LAWS[self.friction.law]
        if faults.free_wheels.any():
            try:
                law.supports(cells, free_wheels=True)
            except ValueError as e:
                raise ScenarioError("faults", str(e)) from None
        three = contacts is not None and contacts.wheel_of.max() >= 2
        if three and self.faults.dead_wheels == "free" and faults.dead_cells.any():
            raise ScenarioError("faults.dead_wheels", "a hexagonal cell's three omni wheels are held when it is dead "
                                "(\"free\" is modelled for two-wheel cells)")
        if three and (faults.stuck_wheels.any() or faults.free_wheels.any()):
            raise ScenarioError("faults", "stuck and free wheels are modelled for two-wheel cells; a hexagonal cell's "
                                "three omni wheels take only whole-cell faults (dead_cells) so far")
        velocities = faults.hold_velocities(velocities, cells.drive_directions)
        if self.faults.events:
            if self.faults.dead_wheels == "free" and any(ev.dead_cells or ev.revived_cells
                                                         for ev in self.faults.events):
                raise ScenarioError("faults.dead_wheels", "\"free\" is for cells dead from the start to the end: "
                                    "a cell an event kills holds its wheels, and one it revives would not drive")
            if self.control is None:
                raise ScenarioError("faults.events", "faults injected during a run need [control] (constant fields "
                                    "have no ticks to inject them at)")
            for k, ev in enumerate(self.faults.events):
                if ev.t >= self.duration:
                    raise ScenarioError(f"faults.events[{k}].t", f"{ev.t} s is not before the end of the run "
                                        f"({self.duration} s)")
                for j, (cell, port) in enumerate(ev.dead_links):
                    if cell < cells.n and port >= cells.ports[cell]:
                        raise ScenarioError(f"faults.events[{k}].dead_links[{j}]",
                                            f"cell {cell} has ports 0..{cells.ports[cell] - 1}")
                if three and ev.stuck_wheels:
                    raise ScenarioError(f"faults.events[{k}].stuck_wheels", "hexagonal cells take whole-cell faults "
                                        "only so far")
        if faults.stuck_on.any() or faults.stuck_off.any():
            sensors = dataclasses.replace(sensors, stuck_on=sensors.stuck_on | faults.stuck_on,
                                          stuck_off=sensors.stuck_off | faults.stuck_off)
        if contacts is not None:
            try:
                law.supports(contacts)
            except ValueError as e:
                raise ScenarioError("array.wheels", str(e)) from None
        if contacts is not None and self.wheels.model == "motor":
            raise ScenarioError("wheels.model", "motor-driven wheels are modelled for the paper's lumped cells "
                                "without belts; use model = \"ideal\" with separate or omni wheels and belts")
        if contacts is None:
            contacts = cells
        if faults.free_wheels.any():  # a free wheel gives no traction: its contact loses that drive direction
            w = contacts.wheel_of
            free = (w >= 0) & faults.free_wheels[contacts.cell_of[:, None], np.maximum(w, 0)]
            contacts = dataclasses.replace(contacts, wheel_active=contacts.wheel_active & ~free)
        present, changes = self._reconfiguration(cells)
        start_layer = contacts if present is None else _present_layer(contacts, present[contacts.cell_of])
        specs, states = [], []
        for i, p in enumerate(self.parcels):
            where = f"parcels[{i}]"
            with _at(where):
                if p.vertices is not None:
                    spec = polygon(p.vertices, p.mass, p.mu, p.com, p.inertia, name=p.name, mu_static=p.mu_static)
                else:
                    spec = rectangle(p.length, p.width, p.mass, p.mu, p.inertia, name=p.name, mu_static=p.mu_static)
            state = np.array([p.x, p.y, p.theta, p.vx, p.vy, p.omega], dtype=float)
            _check_on_array(start_layer, spec, state, where, p.name)
            specs.append(spec)
            states.append(state)
        polys = [s.world_polygon(st) for s, st in zip(specs, states)]
        for i in range(len(polys)):
            for j in range(i + 1, len(polys)):
                if self.parcels[i].t_start > 0 or self.parcels[j].t_start > 0 or self.arrivals == "saturate":
                    continue  # a later arrival waits until its place is free
                if shapely.intersection(polys[i], polys[j]).area > 1e-12:
                    raise ScenarioError(f"parcels[{j}]", f"parcel {self.parcels[j].name!r} overlaps parcel "
                                        f"{self.parcels[i].name!r} at the start; move one of them")
        if self.arrivals == "saturate" and self.control is None:
            raise ScenarioError("arrivals", "saturating the entries needs [control] (a networked run)")
        for i, p in enumerate(self.parcels):
            if p.t_start > 0 and self.control is None:
                raise ScenarioError(f"parcels[{i}].t_start", "parcels arriving later need [control] (a networked run)")
            if p.sequence is not None and (self.control is None or not program_of(self.control).LABELS):
                readers = _either([name for name, m in PROGRAMS.items() if m.LABELS])
                raise ScenarioError(f"parcels[{i}].sequence", f"sequence numbers are for sorting (program {readers})")
        control = None if self.control is None else _build_control(self.control, cells, sensors, specs, states,
                                                                       self.parcels, faults, marks)
        if control is None and self.wheels.model == "motor":
            control = _field_control(cells, velocities, self.wheels.period)
        events, now = [], faults
        for k, ev in sorted(enumerate(self.faults.events), key=lambda e: e[1].t):
            _check_listed_faults(ev, cells.n, sensors.count, f"faults.events[{k}]")
            with _at(f"faults.events[{k}]"):
                now = later(now, ev, cells.n, sensors.count)
            events.append((ev.t, now))
        setup = Setup(self, cells, velocities, law, specs, states, control, sensors, contacts,
                      faults, events, present, changes)
        _check_step(setup)
        _check_memory(setup)
        return setup

    def _reconfiguration(self, cells: layout.CellArray) -> tuple[np.ndarray, list]:
        """(cells present at the start, [(t, cells present from then on), ...] in time order), checked; (None, [])
        for an array that stays as it is."""
        r = self.reconfiguration
        if not (r.absent or r.changes):
            return None, []
        present = np.ones(cells.n, dtype=bool)
        c = self.control
        if c is None or getattr(c, "central", False) or self.wheels.model == "motor":
            raise ScenarioError("reconfiguration", "cells taken out and put in during a run need [control] with a "
                                "distributed program (central = false) and ideal wheels")

        def ids(items, where):
            for k, i in enumerate(items):
                if i >= cells.n or cells.belts[i]:
                    raise ScenarioError(f"{where}[{k}]", f"cell {i} is not a cell of the array (it has "
                                        f"{int((~cells.belts).sum())} cells)")
            return list(items)

        present[ids(r.absent, "reconfiguration.absent")] = False
        out, now = [], present.copy()
        for k, ch in sorted(enumerate(r.changes), key=lambda e: e[1].t):
            where = f"reconfiguration.changes[{k}]"
            if ch.t >= self.duration:
                raise ScenarioError(f"{where}.t", f"{ch.t} s is not before the end of the run ({self.duration} s)")
            now = now.copy()
            for j, i in enumerate(ids(ch.remove, f"{where}.remove")):
                if not now[i]:
                    raise ScenarioError(f"{where}.remove[{j}]", f"cell {i} is not in the array at {ch.t} s")
                now[i] = False
            for j, i in enumerate(ids(ch.add, f"{where}.add")):
                if now[i]:
                    raise ScenarioError(f"{where}.add[{j}]", f"cell {i} is already in the array at {ch.t} s")
                now[i] = True
            out.append((ch.t, now))
        return present, out


STEPS_PER_CELL = 10
"""A fixed step may carry a parcel at most 1/STEPS_PER_CELL of a pitch (see :func:`fastest_speed`)."""


def fastest_speed(setup: "Setup") -> float:
    """The fastest speed (m/s) anything in the scene is known to move at before it runs: the wheels' and belts'
    surface speeds of a constant field, the speed a program's wheels are limited to (its options' ``top_speed()``:
    ``control.speed``, or the diffusion program's ``sources``, which bound every wheel by the maximum principle),
    and the parcels' own starting speeds (a spinning parcel's corners included)."""
    sc = setup.scenario
    speeds = [float(np.max(np.hypot(*setup.contact_velocities.T), initial=0.0))]
    c = sc.control
    if c is not None:
        speeds.append(c.top_speed())
    for p, spec in zip(sc.parcels, setup.specs):
        reach = float(np.max(np.hypot(*spec.footprint.T)))
        speeds.append(float(np.hypot(p.vx, p.vy)) + abs(p.omega) * reach)
    return max(speeds)


def _check_step(setup: "Setup") -> None:
    """``integrator.dt`` must resolve the scene. The fixed step (``mode = "fixed"``, the stick-slip law's steps
    there; in event mode the steps across chattering support changes and of parcels stepped together in contact)
    looks the supports up only at its RK4 stages and logs support changes at its ends: a step that carries a parcel
    across a cell jumps over support changes, and its stages evaluate the parcel where it never was (off its
    supports: with ``dt = 0.5`` s the prototype's box "tipped at t=0 s", its RK4 stage half a metre away). So a
    step carries a parcel at the fastest known speed (:func:`fastest_speed`) at most a tenth of a pitch:
    ``dt <= pitch / (10 v_max)`` (measured on the prototype: at the bound, 0.016 s, fixed RK4 keeps all 37
    support changes of the event-driven run within 1.3 mm; five times it drops support changes, ten times it is
    7 cm off). Where dt is the integration step (fixed mode), it is also at most ``output_dt`` when
    one is given (else the samples would be interpolated between steps and claim a resolution the run never had;
    the default spacing, duration/500, is the program's choice, so there only ``dt <= duration``)."""
    sc = setup.scenario
    dt = sc.integrator.dt
    pitch = setup.cells.pitch
    v = fastest_speed(setup)
    if v > 0 and dt > pitch / (STEPS_PER_CELL * v):
        raise ScenarioError("integrator.dt", f"{dt:g} s cannot resolve the scene: a parcel at the fastest speed "
                            f"({v:g} m/s) would cross {dt * v / pitch:.3g} cells ({pitch:g} m pitch) in one step; "
                            f"the step must be at most pitch / ({STEPS_PER_CELL} x speed) = "
                            f"{pitch / (STEPS_PER_CELL * v):.3g} s")
    if sc.integrator.mode == "fixed" or (setup.law.time_stepper is not None and not setup.law.modes):
        limit, what = (sc.output_dt, "the output spacing (output_dt") if sc.output_dt else (sc.duration, "the run ("
                                                                                              "duration")
        if dt > limit * (1 + 1e-9):
            raise ScenarioError("integrator.dt", f"{dt:g} s is longer than {what} = {limit:g} s): the step must be "
                                "at most that")


def memory_limit() -> int:
    """Bytes a run may plan to hold in memory: half this machine's physical memory (8 GiB where it cannot be
    read)."""
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")) // 2
    except (AttributeError, ValueError, OSError):
        return 8 << 30


def memory_estimate(setup: "Setup") -> dict[str, float]:
    """What a run of ``setup`` will hold in memory (bytes), by the field that drives each part:

    - ``output_dt``: the output samples (times and six states, 56 bytes, per parcel) kept in the trajectories, the
      tables and their Parquet/CSV copies (counted four times), and the sample grid;
    - ``control.period``: networked runs' per-tick network record (12 numbers of 8 bytes a tick);
    - ``sensors.record``: the cell log of recorded networked runs (every cell's sensors, wheel speeds, commands and
      sentence counts every tick: S + 48 bytes a cell);
    - ``integrator.dt``: a constant-field run in fixed-step mode (or with a law that is only time-stepped) keeps
      every step of every parcel (about 200 bytes a step) until it samples them.
    """
    sc = setup.scenario
    parcels = len(setup.specs)
    spacing = sc.output_dt or sc.duration / 500
    samples = np.floor(sc.duration / spacing) + 2
    est = {"output_dt": samples * 8 + samples * parcels * 56 * 4}
    if setup.control is not None:
        ticks = np.ceil(sc.duration / setup.control.period)
        est["control.period"] = ticks * 12 * 8
        if sc.sensors.record:
            est["sensors.record"] = ticks * setup.cells.n * (setup.sensors.count + 48)
    elif sc.integrator.mode == "fixed" or (setup.law.time_stepper is not None and not setup.law.modes):
        est["integrator.dt"] = np.ceil(sc.duration / sc.integrator.dt) * parcels * 200
    return {k: float(v) for k, v in est.items()}


def _size(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return ""


def _check_memory(setup: "Setup") -> None:
    """Refuse, before anything is allocated, a run whose :func:`memory_estimate` exceeds :func:`memory_limit`,
    naming the field that drives the largest part."""
    est = memory_estimate(setup)
    total, limit = sum(est.values()), memory_limit()
    if total > limit:
        field, part = max(est.items(), key=lambda kv: kv[1])
        sc = setup.scenario
        hint = {"output_dt": f"{sc.duration:g} s sampled every {sc.output_dt or sc.duration / 500:g} s",
                "control.period": f"{sc.duration:g} s in control ticks of {sc.control.period if sc.control else 0:g} s",
                "sensors.record": "every cell recorded every control tick",
                "integrator.dt": f"{sc.duration:g} s in fixed steps of {sc.integrator.dt:g} s"}[field]
        raise ScenarioError(field, f"this run would hold about {_size(total)} in memory ({_size(part)} for {hint}), "
                            f"more than the limit of {_size(limit)} (half this machine's memory); sample less "
                            "often or simulate less")


def _present_layer(contacts: layout.CellArray, keep: np.ndarray) -> layout.CellArray:
    """The contacts in ``keep`` alone (to check where parcels start)."""
    return layout.CellArray(contacts.positions[keep], contacts.drive_directions[keep], contacts.pitch, None,
                            contacts.wheel_active[keep], contacts.cell_of[keep], contacts.wheel_of[keep])


def _check_on_array(cells, spec, state, where, name):
    """The parcel must start over supports that can carry it (``cells``: the contact layer)."""
    from virtual_vehicle.physics.contact import solve_support

    support = supporting_cells(spec, state, cells.positions, cells.tree)
    if len(support) == 0:
        raise ScenarioError(f"{where}.x", f"parcel {name!r} starts off the array: no cell lies under it at "
                            f"({state[0]:g}, {state[1]:g}) m; the cells span x {cells.bounds[0]:g}..{cells.bounds[2]:g},"
                            f" y {cells.bounds[1]:g}..{cells.bounds[3]:g} m")
    try:
        solve_support(cells.positions[support], state[:2], spec.mass, lateral_support=cells.is_line)
    except TippingError as exc:
        raise ScenarioError(f"{where}.x", f"parcel {name!r} cannot rest where it starts: {exc}") from None


def _build_array(a) -> tuple[layout.CellArray, layout.CellArray | None, dict]:
    """The cell layer, the contact layer (None when it is the cell layer: the paper's lumped cells) and the map's
    marks (entry / exit cells) of array table ``a``, belts included."""
    if isinstance(a, MixedArray):
        for k, part in enumerate(a.parts):
            if not np.isclose(part.pitch, a.parts[0].pitch, rtol=1e-9):
                raise ScenarioError(f"array.parts[{k}].pitch", f"the parts of a mixed array share one pitch "
                                    f"({a.parts[0].pitch:g} m); this one has {part.pitch:g} m")
        built = [_build_part(part, f"array.parts[{k}]") for k, part in enumerate(a.parts)]
        with _at("array.parts"):
            cells, contacts = layout.combine([(c, t) for c, t, _ in built])
        marks = {key: np.concatenate([m.get(key, np.zeros(c.n, bool)) for c, _, m in built])
                 for key in sorted({key for _, _, m in built for key in m})}
    else:
        cells, contacts, marks = _build_part(a, "array")
    n = cells.n
    for k, b in enumerate(a.belts):  # one at a time, to name the belt at fault: the same array as all at once
        with _at(f"array.belts[{k}]"):
            belt = layout.Belt(b.start, b.end, b.width, b.speed, b.spacing or cells.pitch / 2)
            cells, contacts = layout.with_belts(cells, cells if contacts is None else contacts, [belt])
    if a.belts:
        marks = {k: np.concatenate([m, np.zeros(cells.n - n, bool)]) for k, m in marks.items()}
    return cells, contacts, marks


def _build_part(a, where: str) -> tuple[layout.CellArray, layout.CellArray | None, dict]:
    """Cells, contact layer (None: lumped) and marks of one array table (at TOML path ``where``), without its
    belts."""
    marks = {}
    if isinstance(a, MapArray):
        with _at(f"{where}.map"):
            cells, marks = layout.from_map(a.map, a.pitch, a.origin, a.lattice, a.drive_angle)
    elif isinstance(a, PointsArray):
        with _at(f"{where}.points"):
            cells = layout.from_points(a.points, a.pitch, a.drive_angle)
    else:
        with _at(where):
            if isinstance(a, GridArray):
                cells = layout.grid(a.nx, a.ny, a.pitch, a.origin, a.drive_angle)
            elif isinstance(a, RowArray):
                cells = layout.row(a.n, a.pitch, a.origin, a.drive_angle)
            else:
                cells = layout.hexagonal(a.nx, a.ny, a.pitch, a.origin, a.drive_angle)
    if isinstance(a, HexArray) or getattr(a, "lattice", "square") == "hex":
        with _at(f"{where}.wheel_radius"):
            return cells, layout.three_wheels(cells, a.wheel_radius), marks
    if a.wheels == "separate":
        with _at(f"{where}.wheel_offsets"):
            return cells, layout.separate_wheels(cells, a.wheel_offsets), marks
    return cells, None, marks


def _check_listed_faults(table, n: int, sensors: int, where: str) -> None:
    """Every cell (and sensor) that faults table or event ``table`` (at TOML path ``where``) lists must exist: checked
    here, before the faults are resolved, to name the entry at fault."""
    for name in ("dead_cells", "stuck_wheels", "free_wheels", "stuck_on", "stuck_off", "dead_links"):
        for k, item in enumerate(getattr(table, name, ())):
            cell = item if isinstance(item, int) else item[0]
            if cell >= n:
                raise ScenarioError(f"{where}.{name}[{k}]", f"cell {cell} does not exist (the array has {n})")
            if name in ("stuck_on", "stuck_off") and item[1] >= sensors:
                raise ScenarioError(f"{where}.{name}[{k}]", f"no sensor {item[1]}: cells have {sensors}")


def _build_field(f):
    if isinstance(f, RadialField):
        return fieldlib.Radial(f.center, f.speed)
    if isinstance(f, SqueezeField):
        return fieldlib.Squeeze(f.point, f.direction, f.speed, f.along)
    if isinstance(f, RotationField):
        return fieldlib.Rotation(f.center, f.omega)
    if isinstance(f, TwistField):
        return fieldlib.Twist(f.center, f.twist)
    if isinstance(f, RegionsField):
        return fieldlib.Regions(tuple((r.outline, _build_field(r.field)) for r in f.regions),
                                None if f.default is None else _build_field(f.default))
    if isinstance(f, UniformField):
        return fieldlib.Uniform(f.velocity)
    if isinstance(f, InwardField):
        return fieldlib.Inward(f.center, f.speed)
    if isinstance(f, ReversedEndField):
        return fieldlib.ReversedEnd(f.velocity)
    return fieldlib.PerCell(tuple(f.velocities))


def _build_sensors(spec: SensorSpec, cells: layout.CellArray):
    from virtual_vehicle.cells.hardware import Sensors, default_offsets

    offsets = default_offsets(cells.pitch) if spec.offsets is None else np.asarray(spec.offsets, dtype=float)
    masks = {}
    for name in ("stuck_on", "stuck_off"):
        mask = np.zeros((cells.n, len(offsets)), dtype=bool)
        for k, (cell, sensor) in enumerate(getattr(spec, name)):
            if cell >= cells.n or sensor >= len(offsets):
                raise ScenarioError(f"sensors.{name}[{k}]", f"no sensor {sensor} on cell {cell} ({cells.n} cells, "
                                    f"{len(offsets)} sensors each)")
            mask[cell, sensor] = True
        masks[name] = mask
    with _at("sensors"):
        return Sensors(cells, offsets, spec.false_positive, spec.false_negative, masks["stuck_on"],
                       masks["stuck_off"], spec.seed)


def _field_control(cells: layout.CellArray, velocities: np.ndarray, period: float) -> "ControlSetup":
    """Cells that command their field velocity every period (so that motor wheels can follow it)."""
    from virtual_vehicle.cells.control import FollowField
    from virtual_vehicle.cells.network.delivery import IdealRounds
    from virtual_vehicle.cells.network.topology import from_layout

    topo = from_layout(cells)
    wheels = np.einsum("ij,ikj->ik", velocities, cells.drive_directions)
    return ControlSetup(FollowField(wheels), topo, functools.partial(IdealRounds, topo), "none", period, {})


def _build_control(c, cells: layout.CellArray, sensors, specs, states, parcels, faults, marks) -> ControlSetup:
    """The network every program shares (the topology with its dead cells and links, the delivery model), then
    the program's own builder (its module in :data:`~virtual_vehicle.cells.programs.PROGRAMS`)."""
    from virtual_vehicle.cells.network.delivery import IdealRounds
    from virtual_vehicle.cells.network.topology import from_layout
    from virtual_vehicle.cells.network.wire import WireLevel, WireParams

    topo = from_layout(cells).with_faults(dead_cells=np.flatnonzero(faults.dead_cells), dead_links=faults.dead_links)
    if c.delivery == "ideal":
        make_delivery = functools.partial(IdealRounds, topo, loss_rate=c.loss_rate, seed=c.seed)
    else:
        make_delivery = functools.partial(WireLevel, topo, WireParams(**c.wire.model_dump()), seed=c.seed)
    ctx = BuildContext(cells, sensors, specs, states, parcels, topo, make_delivery, marks)
    try:
        return program_of(c).build(c, ctx)
    except FieldError as exc:
        raise ScenarioError(exc.field, exc.message) from None


@dataclass(frozen=True, eq=False)
class Setup:
    """A validated scenario turned into simulation objects (``control`` is None for a constant field)."""

    scenario: Scenario
    cells: layout.CellArray
    velocities: np.ndarray
    law: FrictionLaw
    specs: list[ParcelSpec]
    states: list[np.ndarray]
    control: ControlSetup | None = None
    sensors: object = None
    contacts: layout.CellArray | None = None
    faults: object = None
    fault_events: list = dataclasses.field(default_factory=list)
    """(t, :class:`~virtual_vehicle.model.faults.Faults` from then on) for each fault event, in time order."""
    present: np.ndarray | None = None
    """(n,) cells installed at the start (None: all); see :class:`ReconfigurationSpec`."""
    cell_changes: list = dataclasses.field(default_factory=list)
    """(t, (n,) cells installed from then on) for each reconfiguration, in time order."""

    def plant(self):
        """A fresh :class:`~virtual_vehicle.engine.plant.Plant` for this scenario's parcels on its contact layer."""
        from virtual_vehicle.engine.plant import Integration, Plant

        sc = self.scenario
        integ = sc.integrator
        return Plant(self.contact_layer, self.specs, self.law, sc.gravity,
                     Integration(integ.mode, integ.rtol, integ.atol, integ.max_step or np.inf, integ.dt, integ.batch),
                     sc.contacts.params())

    @property
    def contact_layer(self) -> layout.CellArray:
        """Where the parcels touch the array: the cells (lumped wheels) or one contact per wheel."""
        return self.cells if self.contacts is None else self.contacts

    @property
    def contact_velocities(self) -> np.ndarray:
        """Surface velocities (m/s) of the contact layer under the constant field."""
        return self.contact_layer.contact_velocities(self.velocities)


_BOUNDS = {"greater_than": ("gt", "greater than"), "greater_than_equal": ("ge", "at least"),
           "less_than": ("lt", "less than"), "less_than_equal": ("le", "at most")}


def _either(names: list[str]) -> str:
    """``"a", "b" or "c"``: names as TOML strings."""
    quoted = [f'"{n}"' for n in names]
    return quoted[0] if len(quoted) == 1 else ", ".join(quoted[:-1]) + " or " + quoted[-1]


def _format_validation(exc: ValidationError) -> ScenarioError:
    lines = []
    first_field = ""
    for err in exc.errors():
        parts, program = list(err["loc"]), None
        if len(parts) >= 2 and parts[0] == "control" and parts[1] in PROGRAMS:
            program = parts.pop(1)  # the tag pydantic adds: the program whose options it checked
        loc = ""
        for part in parts:
            if isinstance(part, int):
                loc += f"[{part}]"
            else:
                loc += ("." if loc else "") + str(part)
        # drop the discriminator tag pydantic adds to union locations
        for tag in ("grid", "row", "points", "hex", "map", "mixed", "uniform", "inward", "reversed_end", "per_cell",
                    "radial", "squeeze", "rotation", "twist", "regions"):
            loc = loc.replace(f".{tag}.", ".").removesuffix(f".{tag}")
        msg = err["msg"]
        names = _either(list(PROGRAMS))
        if err["type"] == "extra_forbidden" and program is not None and len(parts) == 2 and owners(parts[1]):
            msg = (f'is a field of program {_either(owners(parts[1]))}, not of program "{program}" (see the scenario '
                   "format)")
        elif err["type"] == "extra_forbidden":
            msg = "unknown field (check its spelling against the scenario format)"
        elif err["type"] == "union_tag_invalid" and err.get("ctx", {}).get("discriminator") == "'program'":
            loc += ".program"
            msg = f"unknown program \"{err['ctx'].get('tag')}\"; the programs are {names}"
        elif err["type"] == "union_tag_not_found" and err.get("ctx", {}).get("discriminator") == "'program'":
            loc += ".program"
            msg = f"missing: name the program every cell runs, one of {names}"
        elif err["type"] in _BOUNDS and isinstance(err.get("ctx", {}).get(_BOUNDS[err["type"]][0]), (int, float)):
            key, words = _BOUNDS[err["type"]]
            bound, given = err["ctx"][key], err.get("input")
            if key == "ge" and 0 < bound <= 1e-6 and isinstance(given, (int, float)) and given <= 0:
                # a tiny floor is there against underflow; what a zero or negative value lacks is its sign
                msg = f"must be positive (at least {bound:g}), got {given!r}"
            else:
                msg = f"must be {words} {bound:g}, got {given!r}"
        elif err["type"] == "union_tag_invalid":
            msg = f"unknown kind {err.get('input', {}).get('kind') if isinstance(err.get('input'), dict) else ''!r}; " + msg
        first_field = first_field or loc
        lines.append(f"{loc}: {msg}" if loc else msg)
    text = lines[0] if len(lines) == 1 else "\n".join([f"{len(lines)} problems:"] + [f"  {ln}" for ln in lines])
    err = ScenarioError("", text)
    err.field = first_field
    return err


def parse_scenario(data: dict) -> Scenario:
    """Validate a scenario given as a dict (as read from TOML). Raises ScenarioError."""
    if not isinstance(data, dict):
        raise ScenarioError("", "a scenario must be a table of fields")
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise _format_validation(exc) from None


def bundled_scenarios() -> dict[str, str]:
    """Names and one-line descriptions of the scenarios shipped with the package."""
    out = {}
    for entry in sorted(resources.files("virtual_vehicle.config.scenarios").iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            out[entry.name.removesuffix(".toml")] = str(data.get("description", "")).strip().splitlines()[0] if data.get("description") else ""
    return out


DEFAULT_SCENARIO = "prototype_18"
"""The scenario ``virtual-vehicle run`` uses when none is named."""


def load_scenario(source: str | Path | None = None) -> tuple[Scenario, str]:
    """Load and validate a scenario from a TOML file path or a bundled scenario's name (default:
    :data:`DEFAULT_SCENARIO`). Returns the scenario and its TOML text. Raises ScenarioError."""
    source = DEFAULT_SCENARIO if source is None else source
    path = Path(source)
    if path.is_dir():
        raise ScenarioError("", f"{str(path)!r} is a directory, not a scenario file: name a .toml file (or a bundled "
                            "scenario)")
    if path.is_file():
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ScenarioError("", f"cannot read scenario file {str(path)!r}: {exc}") from None
    else:
        name = str(source).removesuffix(".toml")
        res = resources.files("virtual_vehicle.config.scenarios").joinpath(f"{name}.toml")
        if "/" in name or not res.is_file():
            raise ScenarioError("", f"no scenario file or bundled scenario named {str(source)!r}; bundled: "
                                f"{', '.join(bundled_scenarios())}")
        text = res.read_text(encoding="utf-8")
    return parse_text(text, str(source)), text


def parse_text(text: str, where: str = "scenario") -> Scenario:
    """Validate a scenario given as TOML text. Raises ScenarioError (malformed TOML included)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError("", f"{where} is not valid TOML: {exc}") from None
    return parse_scenario(data)


def dump_toml(scenario: Scenario) -> str:
    """A scenario as TOML text that :func:`parse_text` reads back to an equal scenario (fields left at None are
    left out, so they take their defaults again).

    >>> sc = load_scenario("paper_2x2_inward")[0]
    >>> parse_text(dump_toml(sc)) == sc
    True
    """
    import tomli_w

    return tomli_w.dumps(scenario.model_dump(mode="json", exclude_none=True), multiline_strings=True)
