"""The contract every friction law keeps: what the engine, the planner, field design, equilibria, scaling and the
scenario ask of a law, so that none of them asks which law it holds.

Units: N, N m, m, m/s, rad/s, s. Torques are about the vertical axis through the parcel's centre of mass,
counter-clockwise positive. A parcel's state is ``(x, y, theta, vx, vy, omega)``.

A law is either *event-driven* (``time_stepper`` None): on one set of supports its wrench is affine in the parcel's
state, given by a piece's constants (:mod:`~virtual_vehicle.physics.laws.affine`), and the event-driven engine
integrates it between support changes; or it has *modes* of its own (wheels sticking or slipping, ``modes``): the
event-driven engine then integrates it mode by mode from its wheels (:meth:`FrictionLaw.wheel_contacts`, the
exact modes of :mod:`~virtual_vehicle.physics.stick_modes`), and it names the engine's time stepper that solves it
every step instead (``time_stepper``: fixed mode, and a group's contact problem when parcels push each other).
Either way :meth:`FrictionLaw.constants` gives the
per-support-set constants (for a time-stepped law, those of one mode, for reference) and
:meth:`FrictionLaw.cell_forces` the exact per-cell forces of a state, which
:func:`~virtual_vehicle.physics.laws.check_law` checks.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import NamedTuple

import numpy as np

from virtual_vehicle.physics.contact import SupportSolution
from virtual_vehicle.physics.laws.affine import FrictionConstants, cell_wrench


def energy_reach(start, grown, window):
    """How far (m) and how fast (m/s) a point can go in ``window`` s when its speed squared grows at most linearly,
    from ``start`` to ``grown`` (m^2/s^2, arrays or floats), as the energy bounds of the laws that dissipate give it:
    the speed bound ``sqrt(grown)`` and its integral ``(2 T / 3) (x + sqrt(x y) + y) / (sqrt(x) + sqrt(y))`` with
    ``y`` = ``start``, ``x`` = ``grown`` (written without the difference of two powers, which loses digits where
    the speed hardly grows), 0 where both are 0."""
    rx, ry = np.sqrt(grown), np.sqrt(start)
    both = rx + ry
    dist = np.where(both > 0, (2.0 / 3.0) * window * (grown + rx * ry + start) / np.where(both > 0, both, 1.0), 0.0)
    return dist, rx


def rotating_reach(rho0, u0_sq, omega: float, lever, window):
    """Upper bounds on how far (m) any point of a parcel can move in ``window`` s relative to a frame rotating at
    ``omega`` (rad/s, not 0) about a centre, and on the speed (m/s) any point can reach relative to it, elementwise
    over arrays: ``rho0`` the centre of mass's distance from the centre (m), ``u0_sq`` (m^2/s^2) twice its kinetic
    energy relative to the frame over its mass, ``|v - omega x r|^2 + (I / m) (Omega - omega)^2``, plus twice the
    work the wheels can do in the window over the mass (``2 P T / m``, ``P`` the law's
    :meth:`FrictionLaw.frame_power`), and ``lever`` ``1 + m R^2 / I``.

    In the rotating frame the wheels' work is at most ``P T``, the Coriolis force does none and the centrifugal
    force's is ``m omega^2 (rho^2 - rho0^2) / 2`` (a rigid body's ``sum m_i |r_i|^2`` is ``m rho^2 + I``), so the
    relative kinetic energy E has ``2 E / m <= u0_sq + omega^2 (rho^2 - rho0^2)``. The centre of mass's distance then
    grows no faster than the largest solution of ``rho' = sqrt(u0_sq + omega^2 (rho^2 - rho0^2))``,
    ``rho_B = rho0 cosh(|omega| t) + sqrt(u0_sq) sinh(|omega| t) / |omega|``, and its relative speed is at most
    ``rho_B'``; a point's is at most ``sqrt(lever)`` times that (``|v| + R |Omega| <= sqrt(lever 2 E / m)``), so
    it moves at most ``sqrt(lever) (rho_B - rho0)``. A parcel riding the field (``u0_sq`` 0) drifts at most
    ``rho0 (cosh(omega T) - 1)``, second order in T, where a translating frame's bound grows with the spread of the
    wheel speeds over the whole array."""
    a = abs(float(omega))
    T = np.asarray(window, dtype=float)
    u0 = np.sqrt(u0_sq)
    grown = rho0 * 2.0 * np.sinh(0.5 * a * T) ** 2 + u0 * np.sinh(a * T) / a  # rho_B - rho0 (cosh - 1 = 2 sinh^2)
    rate = np.sqrt(u0_sq + a * a * grown * (grown + 2.0 * rho0))  # rho_B' (rho_B^2 - rho0^2 = g (g + 2 rho0))
    root = np.sqrt(lever)
    return root * grown, root * rate


class StepperOptions(NamedTuple):
    """What a time-stepped law hands the engine's stepper for the contact problem it solves every step (the wheels'
    own, and a group's when parcels push each other): the projected Gauss-Seidel solver's limits."""

    max_sweeps: int
    """Most sweeps over the rows before a step is given up as unconverged."""
    tolerance: float
    """Convergence: the largest change of an impulse in a sweep, relative to the largest impulse bound."""


class FrictionLaw(ABC):
    """A friction law: from normal forces (N) and wheel velocities (m/s) to the forces on a parcel, and everything
    else the simulator needs that depends on the law. Subclasses are frozen dataclasses (hashable, comparable)."""

    name: str
    """As written in scenario files (``[friction] law``)."""
    time_stepper: str | None = None
    """None: event-driven (affine constants per piece). Else the name of the engine's time stepper for the law."""
    modes: bool = False
    """True for a law with modes of its own (each wheel sticks or slips): the event engine then integrates it mode
    by mode on each support set, from the wheels :meth:`wheel_contacts` gives, and its ``time_stepper`` is the
    fixed-step alternative (fixed mode, and parcels stepped together in contact)."""
    assumes_sliding: bool = False
    """True when the law's forces hold only while every wheel slides under the parcel in its direction of spin
    (the parcel slower than its wheels): a run then checks that assumption along each trajectory."""
    damped: bool = False
    """True when the wrench damps the parcel's twist (a force against its velocity): equilibria are then
    classified by the stiffness alone (a damped node or focus); undamped ones are centres at best."""
    galilean: bool = False
    """True when the forces depend on the wheels' and the parcel's velocities only through the slip between them:
    seen from a frame moving at a constant velocity the law is the same, with the wheel velocities taken in that
    frame, so :meth:`reach` bounds motion relative to it (the planner then bounds how far parcels move relative
    to the wheels' common velocity, which on a uniform field is how far they stray from riding it)."""

    def stepper_options(self) -> StepperOptions | None:
        """What the law's time stepper takes from it (:class:`StepperOptions`), so that the engine asks the law no
        attribute of its own; None for an event-driven law (``time_stepper`` None), which a time-stepped law
        overrides."""
        return None

    @abstractmethod
    def drive_vectors(self, velocities: np.ndarray, drive_directions: np.ndarray) -> np.ndarray:
        """(n, 2) the per-cell drive vector the law's constants are built from, from cell velocities (n, 2) m/s and
        drive directions (n, k, 2)."""

    @abstractmethod
    def cell_forces(self, points, normal, velocities, drive_directions, mu: float, state) -> np.ndarray:
        """(m, 2) the horizontal force (N) each supporting cell at ``points`` (m) with normal force ``normal`` (N)
        exerts on the parcel in ``state``."""

    def wrench(self, points, normal, velocities, drive_directions, mu: float, state) -> tuple[float, float, float]:
        """The net horizontal force (N, N) and torque (N m, about the centre of mass) on the parcel by direct
        summation of :meth:`cell_forces` (eqs. 22, 24)."""
        return cell_wrench(points, self.cell_forces(points, normal, velocities, drive_directions, mu, state),
                           state[:2])

    @abstractmethod
    def constants(self, solution: SupportSolution, velocities: np.ndarray, drive_directions: np.ndarray,
                  mu: float) -> FrictionConstants:
        """The per-support-set constants of a solved support set: the parcel's wrench is then affine in its
        state."""

    @abstractmethod
    def constants_and_row(self, solution: SupportSolution, velocities: np.ndarray, drive_directions: np.ndarray,
                          mu: float, mass: float, inertia: float) -> tuple[FrictionConstants, tuple[float, ...]]:
        """:meth:`constants` and the piece's constants row (:data:`~virtual_vehicle.physics.laws.affine.ROW_FIELDS`)
        for a parcel of ``mass`` (kg) and ``inertia`` (kg m^2)."""

    drive_kernel = None
    """For a law whose :meth:`constants_and_row` is :func:`~virtual_vehicle.physics.laws.affine._terms_and_row` of
    drive vectors computed per cell: those drive vectors as a compiled function of the supporting cells' velocities
    ((m, 2), m/s) and drive directions ((m, k, 2)), with :meth:`affine_damping` as the damping, so that the compiled
    event loop makes a new support set's constants without Python (and exactly as :meth:`constants_and_row` does).
    None: every new support set's constants are made in Python."""

    def affine_damping(self, mu: float) -> float:
        """The damping :meth:`constants_and_row` passes with :attr:`drive_kernel` for friction coefficient ``mu``."""
        raise NotImplementedError(f"the {self.name} law has no compiled drive")

    @abstractmethod
    def reach(self, s0, window, *, rate, wheel_speed: float, lever=None):
        """Upper bounds on how far (m) any point of a parcel can move in ``window`` s driven by the wheels alone,
        and on the speed (m/s) any point can reach in that time, on floats or arrays (elementwise).

        ``s0``: the fastest point speed now, ``|v| + |omega| R`` (m/s, R the footprint radius); ``rate``:
        ``mu_max g (1 + m R^2 / I)``, the law's friction coefficient times gravity times the lever of the rim
        (m/s^2 per unit of the law's drive); ``wheel_speed``: the fastest wheel surface speed (m/s); ``lever``:
        that lever ``1 + m R^2 / I`` (dimensionless) when the caller knows it (None: a bound without it). The
        normal forces under a parcel sum to its weight (paper eqs. 3-5) and every cell lies within R of its centre
        of mass. The planner's safety proof rests on this being a true bound."""

    def frame_power(self, mu_weight, wheel_slack):
        """An upper bound on the power (W) the wheels can put into a parcel seen from a frame that may rotate, on
        floats or arrays (elementwise), or None when the law gives none. ``mu_weight``: the parcel's largest
        friction coefficient times its weight (N, or N s/m for a coefficient in s/m); ``wheel_slack``: how far the
        wheels are from standing still in the frame (m/s): at least every entry's surface speed relative to the frame
        at the entry, and the sum, over its wheels, of that along their drive directions
        (:func:`~virtual_vehicle.physics.collide.rigid_rotation`'s slack). A law whose
        wheels only take energy out of a parcel that moves relative to them (friction dissipates in the frame in
        which the wheels stand still) bounds it; the planner then measures how far parcels stray from a rigidly
        rotating field in the field's own frame (:func:`rotating_reach`), where a
        parcel riding it stays put. None by default: the planner measures in a translating frame only."""
        return None

    def drive_bound(self, velocities: np.ndarray, drive_directions: np.ndarray) -> float:
        """The largest per-cell drive vector's length under wheels ``velocities`` (m/s) on one support set, which
        :meth:`piece_reach` takes as ``drive``."""
        drive = self.drive_vectors(velocities, drive_directions)
        return float(np.max(np.hypot(drive[:, 0], drive[:, 1])))

    def piece_reach(self, rate, window: float, curve, drive, slip):
        """What the parcel's acceleration adds to ``S0 T`` (m) over ``window`` s while one piece holds: ``rate``
        as in :meth:`reach` (1/s or m/s^2 per unit drive, arrays), ``curve`` a bound on the centripetal terms
        (m/s^2), ``drive`` :meth:`drive_bound` of the piece's wheels, ``slip`` a callable giving the largest slip
        speed (m/s) under each parcel now (computed only when asked). Infinite by default: no bound of the
        piece's own, the law's :meth:`reach` alone."""
        return np.full(np.shape(rate), np.inf)

    @abstractmethod
    def wheel_loads(self, speed: np.ndarray, slip: np.ndarray) -> np.ndarray:
        """The force of each wheel along its drive direction per unit ``mu N``, from its surface speed ``speed``
        (m/s) and the slip along it (wheel speed less the parcel's speed there, m/s)."""

    @abstractmethod
    def scaled_mu(self, mu: float, length: float) -> float:
        """The friction coefficient that keeps a run similar when every length is multiplied by ``length`` and
        times by its square root (Froude scaling)."""

    def wheel_contacts(self, cells, support, solution, velocities, mu: float, mu_static: float | None = None):
        """For a law with :attr:`modes`: the wheels of the entries ``support`` of ``cells`` on their solved support
        set ``solution``, each a 1-D friction contact (a :class:`~virtual_vehicle.physics.stick_modes.Wheels`),
        under surface velocities ``velocities`` ((n, 2) m/s, all entries), kinetic ``mu`` and static
        ``mu_static``. Raises ValueError for a law without modes."""
        raise ValueError(f"the {self.name} law has no modes")

    def wheel_arrays(self, cells, support, solution, velocities, mu: float, mu_static: float | None = None) -> tuple:
        """:meth:`wheel_contacts` as the plain arrays the compiled mode decision takes
        (:func:`~virtual_vehicle.physics.stick_modes.wheel_arrays`), built without objects: what the engine asks at
        every support change. Raises ValueError for a law without modes."""
        raise ValueError(f"the {self.name} law has no modes")

    def supports(self, cells, free_wheels: bool = False) -> None:
        """Raise ValueError when the law cannot act on ``cells`` (a contact layer: lumped cells, or one contact per
        wheel when ``cells.separate``) or on free-spinning wheels (``free_wheels``). Every geometry by default."""

    def design_wheels(self, A: np.ndarray, own: np.ndarray, want: np.ndarray, vmax: float):
        """Wheel speeds ``x`` (2m,) within +-``vmax`` (m/s) whose wrench comes closest to ``want`` (N, N, N m), and
        that wrench: ``A`` (3, 2m) is the wrench per unit ``mu N`` of each wheel, ``own`` (2m,) the parcel's own
        speed along each wheel's drive direction (m/s). Raises ValueError for a law without a design."""
        raise ValueError(f"the {self.name} law has no wrench design")
