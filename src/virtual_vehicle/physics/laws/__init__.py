"""Friction laws (paper Sections 4.3, 4.4, 5), one module each, behind one contract
(:class:`~virtual_vehicle.physics.laws.base.FrictionLaw`), in one registry (:data:`LAWS`), each checked by
:func:`check_law`.

A new law is a module with a :class:`FrictionLaw` subclass and one line in :data:`LAWS`; it must pass
:func:`check_law`.
"""

from __future__ import annotations

import copy

import numpy as np

from virtual_vehicle.physics.contact import solve_support
from virtual_vehicle.physics.laws import affine
from virtual_vehicle.physics.laws.affine import J, FrictionConstants, drive_constants
from virtual_vehicle.physics.laws.base import FrictionLaw, StepperOptions, rotating_reach
from virtual_vehicle.physics.laws.coulomb import CoulombLaw, coulomb_constants
from virtual_vehicle.physics.laws.stick_slip import StickSlipLaw
from virtual_vehicle.physics.laws.viscous import ViscousLaw, viscous_constants
from virtual_vehicle.physics.stick_modes import box_sweeps

LAWS: dict[str, FrictionLaw] = {
    "coulomb": CoulombLaw(),
    "viscous": ViscousLaw(),
    "stick_slip": StickSlipLaw(),
}
"""Friction laws by name, as written in scenario files."""


def law_named(name: str) -> FrictionLaw:
    """The registered law ``name``; ValueError naming the choices for any other."""
    try:
        return LAWS[name]
    except KeyError:
        raise ValueError(f"unknown friction law {name!r}: one of {', '.join(map(repr, LAWS))}") from None


def _rotation(phi: float) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    return np.array([[c, -s], [s, c]])


def _point_velocities(r, v, omega):
    """Velocities (m/s) of points at levers ``r`` ((m, 2), m) from a centre of mass moving at ``v``, spinning at
    ``omega``."""
    return v + omega * np.column_stack([-r[:, 1], r[:, 0]])


class _Trial:
    """One random parcel on random wheels: ``m`` cells within the footprint radius ``R`` (m) of the centre of mass
    carrying normal forces that sum to the weight (N), each with two orthogonal wheels turning at 0.1-1 m/s."""

    def __init__(self, rng: np.random.Generator, mu: float, gravity: float):
        self.mu, self.gravity = mu, gravity
        m = int(rng.integers(3, 9))
        self.R = rng.uniform(0.1, 0.5)
        radius = self.R * np.sqrt(rng.uniform(0.0, 0.81, m))
        angle = rng.uniform(0.0, 2 * np.pi, m)
        self.levers = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])  # body frame, m
        self.mass = rng.uniform(0.5, 20.0)
        self.inertia = self.mass * self.R ** 2 * rng.uniform(0.15, 0.6)
        self.weight = self.mass * gravity
        self.normal = rng.dirichlet(np.ones(m)) * self.weight
        self.U = np.stack([_rotation(a).T for a in rng.uniform(0.0, 2 * np.pi, m)])  # (m, 2, 2) rows: directions
        speeds = rng.uniform(0.1, 1.0, (m, 2)) * rng.choice([-1.0, 1.0], (m, 2))
        self.V = np.einsum("ik,ikj->ij", speeds, self.U)
        self.slowest = float(np.abs(speeds).min())
        self.state = np.array([*rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi), 0.0, 0.0, 0.0])

    def points(self, y):
        return y[:2] + self.levers @ _rotation(y[2]).T

    def forces(self, law: FrictionLaw, y, wheels=None):
        V = self.V if wheels is None else wheels(self.points(y))
        return law.cell_forces(self.points(y), self.normal, V, self.U, self.mu, y)

    def rate(self, law: FrictionLaw, y, wheels=None):
        """State derivative under the law's cell forces, the contact points fixed to the parcel (``wheels``: as
        :func:`_run`'s)."""
        fx, fy, tau = affine.cell_wrench(self.points(y), self.forces(law, y, wheels), y[:2])
        return np.array([y[3], y[4], y[5], fx / self.mass, fy / self.mass, tau / self.inertia])


def _run(trial: _Trial, law: FrictionLaw, y0, window: float, steps: int, wheels=None):
    """RK4 states (steps + 1, 6) of the trial's parcel from ``y0`` over ``window`` s under ``law``;
    ``wheels(points)`` (m -> (m, 2) m/s): the wheels' velocities under the contact points where they are (default:
    the trial's, fixed)."""
    h = window / steps
    ys = [np.asarray(y0, dtype=float)]
    for _ in range(steps):
        y = ys[-1]
        k1 = trial.rate(law, y, wheels)
        k2 = trial.rate(law, y + 0.5 * h * k1, wheels)
        k3 = trial.rate(law, y + 0.5 * h * k2, wheels)
        k4 = trial.rate(law, y + h * k3, wheels)
        ys.append(y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4))
    return np.array(ys)


def _stepped(trial: _Trial, y0, window: float, steps: int, wheels=None):
    """States (steps + 1, 6) of the trial's parcel from ``y0`` over ``window`` s under a law with modes: each wheel a
    1-D friction contact along its drive direction, its impulse in a step of length h within ``mu N h`` (eq. 21 per
    wheel), their impulses the box problem's (projected Gauss-Seidel from zero, which never lets the kinetic energy
    gain more than the wheels' work), then semi-implicit Euler: the law's own exact dynamics to first order, with
    sticking and slipping decided every step. ``wheels(points)`` (m -> (m, 2) m/s): the wheels' velocities under
    the contact points where they are (default: the trial's, fixed)."""
    h = window / steps
    minv = np.array([1.0 / trial.mass, 1.0 / trial.mass, 1.0 / trial.inertia])
    U = trial.U.reshape(-1, 2)  # (2m, 2): each contact's two wheels
    target = np.einsum("ij,ij->i", np.repeat(trial.V, 2, axis=0), U)  # the wheels' surface speeds (m/s)
    bounds = trial.mu * np.repeat(trial.normal, 2) * h
    ys = [np.asarray(y0, dtype=float)]
    for _ in range(steps):
        y = ys[-1]
        if wheels is not None:
            target = np.einsum("ij,ij->i", np.repeat(wheels(trial.points(y)), 2, axis=0), U)
        r = np.repeat(trial.points(y) - y[:2], 2, axis=0)
        J = np.column_stack([U, r[:, 0] * U[:, 1] - r[:, 1] * U[:, 0]])  # [u, r x u]
        nu = box_sweeps(J, minv, y[3:6].copy(), target, bounds, (J * J) @ minv, 1000, 1e-12)
        ys.append(np.array([*(y[:3] + h * nu), *nu]))
    return np.array(ys)


def _reach_holds(law: FrictionLaw, t: _Trial, y0, window: float, steps: int, frame, what: str) -> None:
    """Assert that ``law.reach`` bounds how far the trial's points move from ``y0`` in ``window`` s, and how fast,
    relative to a frame moving at ``frame`` (m/s; the reach then takes speeds relative to it): by RK4 on the law's
    cell forces, or for a law with modes by its wheels stepped (:func:`_stepped`; a first-order step moves its
    points at the speed the step ends with, so a bound that grows is read one step later, where its integral still
    covers the steps' sum)."""
    if law.modes:
        ys, lag = _stepped(t, y0, window, steps), window / steps
    else:
        ys, lag = _run(t, law, y0, window, steps), 0.0
    times = np.linspace(0.0, window, steps + 1)
    lever = 1.0 + t.mass * t.R * t.R / t.inertia
    s0 = float(np.hypot(*(y0[3:5] - frame)) + abs(y0[5]) * t.R)
    wheels = float(np.max(np.hypot(*(t.V - frame).T)))
    dist, speed = law.reach(s0, times + lag, rate=t.mu * t.gravity * lever, wheel_speed=wheels, lever=lever)
    rim = t.R * np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 16, endpoint=False)),
                                 np.sin(np.linspace(0, 2 * np.pi, 16, endpoint=False))])
    body = np.vstack([rim, t.levers])
    start = y0[:2] + body @ _rotation(y0[2]).T
    for j, yj in enumerate(ys):
        moved_by = np.max(np.hypot(*(yj[:2] - frame * times[j] + body @ _rotation(yj[2]).T - start).T))
        fastest = np.hypot(*(yj[3:5] - frame)) + abs(yj[5]) * t.R
        assert moved_by <= dist[j] * (1 + 1e-9) + 1e-12 and fastest <= speed[j] * (1 + 1e-9) + 1e-12, \
            f"{what}: after {times[j]:g} s a point moved {moved_by} m at up to {fastest} m/s, beyond the law's " \
            f"reach bound ({dist[j]} m, {speed[j]} m/s)"


def _turning_reach_holds(law: FrictionLaw, t: _Trial, rng: np.random.Generator, steps: int, what: str,
                         off_by: float, twist: float) -> None:
    """Assert that :func:`rotating_reach` with the law's :meth:`FrictionLaw.frame_power` bounds how far the trial's
    points move, and how fast, relative to a frame rotating at a random rate about a random centre, on wheels that
    turn with it (each at the frame's velocity under its contact point, plus a random slack of up to ``off_by``
    m/s a wheel), from a random twist relative to it (``twist`` m/s and rad/s its scale, 0: riding): a law with modes
    by its wheels stepped (:func:`_stepped`), another by RK4 on its cell forces (:func:`_run`)."""
    omega = rng.uniform(0.3, 2.0) * rng.choice([-1.0, 1.0])
    centre = rng.uniform(-2.0, 2.0, 2)
    slack = rng.uniform(0.0, off_by, (len(t.levers), 2)) * rng.choice([-1.0, 1.0], (len(t.levers), 2))
    off = np.einsum("ik,ikj->ij", slack, t.U)  # each wheel's own speed off the frame's, along its direction

    def carried(P):  # the frame's velocity at points P, plus each wheel's slack
        r = P - centre
        return omega * np.column_stack([-r[:, 1], r[:, 0]]) + off

    r0 = t.state[:2] - centre
    y0 = np.array([*t.state[:3], *(omega * np.array([-r0[1], r0[0]]) + twist * rng.normal(0.0, 1.0, 2)),
                   omega + 1.7 * twist * rng.normal(0.0, 1.0)])
    window = rng.uniform(0.2, 2.0)
    if law.modes:
        ys, lag = _stepped(t, y0, window, 2 * steps, carried), window / (2 * steps)
    else:
        ys, lag = _run(t, law, y0, window, 2 * steps, carried), 0.0
    times = np.linspace(0.0, window, 2 * steps + 1)
    lever = 1.0 + t.mass * t.R * t.R / t.inertia
    power = law.frame_power(t.mu * t.weight, float(np.max(np.sum(np.abs(slack), axis=1))))
    rel = y0[3:5] - omega * np.array([-r0[1], r0[0]])
    energy = rel @ rel + t.inertia / t.mass * (y0[5] - omega) ** 2
    T = times + lag
    dist, speed = rotating_reach(np.hypot(*r0), energy + 2.0 * power * T / t.mass, omega, lever, T)
    rim = t.R * np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 16, endpoint=False)),
                                 np.sin(np.linspace(0, 2 * np.pi, 16, endpoint=False))])
    body = np.vstack([rim, t.levers])
    start = y0[:2] + body @ _rotation(y0[2]).T
    for j, yj in enumerate(ys):
        back = _rotation(-omega * times[j])  # world -> the frame, which started aligned with it
        moved_by = np.max(np.hypot(*((yj[:2] + body @ _rotation(yj[2]).T - centre) @ back.T + centre - start).T))
        r = yj[:2] - centre
        fastest = np.hypot(*(yj[3:5] - omega * np.array([-r[1], r[0]]))) + abs(yj[5] - omega) * t.R
        assert moved_by <= dist[j] * (1 + 1e-9) + 1e-12 and fastest <= speed[j] * (1 + 1e-9) + 1e-12, \
            f"{what}: after {times[j]:g} s a point moved {moved_by} m at up to {fastest} m/s relative to the " \
            f"turning frame, beyond the bound ({dist[j]} m, {speed[j]} m/s)"


def check_law(law: FrictionLaw, trials: int = 20, seed: int = 0, mu: float = 0.5, gravity: float = 9.81,
              steps: int = 200) -> None:
    """Check ``law`` against the friction-law contract on ``trials`` random parcels (``mu`` in the law's units,
    ``gravity`` m/s^2). Raises AssertionError at the first failure.

    - equilibrium: a parcel at rest on wheels at rest feels no force and no torque;
    - rigid-motion invariance: rotating and translating the cells, the wheels and the parcel together rotates the
      force with them and leaves the torque;
    - dissipation: while the parcel is slower than its wheels (the paper's conveying regime) the contacts take
      energy out (slip power >= 0) and, from rest, never more than the wheels put in;
    - the reach bound (:meth:`FrictionLaw.reach`, given the parcel's lever) holds against the motion integrated
      (RK4 on the cell forces, ``steps`` a window; a law with modes: its wheels stepped) from random twists, over
      short windows and long ones (1-3 s, from faster twists), and for a law that says it is relative to its wheels
      (:attr:`FrictionLaw.galilean`) also on wheels all carried at a random common velocity, measured in the frame
      moving with them;
    - a law that bounds its wheels' power in a turning frame (:meth:`FrictionLaw.frame_power`): that bound, through
      :func:`rotating_reach`, holds against the motion (stepped or RK4, as above) of a parcel on wheels that turn
      rigidly, from random twists on wheels a little off the rotation and from riding it on wheels well off it,
      measured in the frame turning with them;
    - an event-driven law's constants give its wrench, and its row is those constants' (:data:`affine.ROW_FIELDS`);
    - a time-stepped law hands its stepper its options (:meth:`FrictionLaw.stepper_options`), an event-driven one
      none.
    """
    assert isinstance(law.name, str) and law.name, "a law has a name"
    options = law.stepper_options()
    if law.time_stepper is None:
        assert options is None, "an event-driven law hands no time stepper options"
    else:
        assert isinstance(options, StepperOptions) and int(options.max_sweeps) >= 1 and options.tolerance > 0, \
            f"a time-stepped law hands its stepper StepperOptions with max_sweeps >= 1, tolerance > 0: {options}"
    rng = np.random.default_rng(seed)
    for k in range(trials):
        t = _Trial(rng, mu, gravity)
        y = t.state
        P = t.points(y)
        scale = mu * t.weight * (1.0 + t.R)
        tol = 1e-9 * scale

        # equilibrium
        rest = law.wrench(P, t.normal, np.zeros_like(t.V), t.U, mu, y)
        assert np.all(np.abs(rest) <= 1e-12 * scale), f"trial {k}: a parcel at rest on stopped wheels feels {rest}"

        # rigid-motion invariance, with the parcel moving slower than its wheels
        twist = rng.normal(size=3)
        twist *= 0.5 * t.slowest / (np.hypot(twist[0], twist[1]) + abs(twist[2]) * t.R)
        y = np.array([*y[:3], *twist])
        phi, shift = rng.uniform(-np.pi, np.pi), rng.uniform(-3, 3, 2)
        Q = _rotation(phi)
        moved = np.array([*(Q @ y[:2] + shift), y[2] + phi, *(Q @ y[3:5]), y[5]])
        w0 = np.array(law.wrench(P, t.normal, t.V, t.U, mu, y))
        w1 = np.array(law.wrench(P @ Q.T + shift, t.normal, t.V @ Q.T, t.U @ Q.T, mu, moved))
        assert np.allclose(w1[:2], Q @ w0[:2], rtol=1e-9, atol=tol) and abs(w1[2] - w0[2]) <= tol + 1e-9 * abs(
            w0[2]), f"trial {k}: the wrench {w0} moved rigidly became {w1}, not {[*(Q @ w0[:2]), w0[2]]}"

        # dissipation, at this state and along a start from rest
        def powers(y):
            F = law.cell_forces(t.points(y), t.normal, t.V, t.U, mu, y)
            u = _point_velocities(t.points(y) - y[:2], y[3:5], y[5])
            return float(np.sum(F * t.V)), float(np.sum(F * (t.V - u))), float(np.max(np.hypot(u[:, 0], u[:, 1])))

        wheel, lost, _ = powers(y)
        assert lost >= -tol, f"trial {k}: the contacts give the parcel {-lost} W of their own"
        window = rng.uniform(0.01, 0.5)
        ys = _run(t, law, np.array([*t.state[:3], 0.0, 0.0, 0.0]), window, steps)
        work = dissipated = 0.0
        for j, yj in enumerate(ys):
            wheel, lost, fastest = powers(yj)
            if fastest > 0.5 * t.slowest:  # no longer the conveying regime
                break
            assert lost >= -tol, f"trial {k}: from rest, at {j * window / steps:g} s the contacts give {-lost} W"
            work, dissipated = work + wheel, dissipated + lost
        assert dissipated <= work + tol, f"trial {k}: from rest the contacts took {dissipated} (x dt), more than " \
                                         f"the wheels' work {work}"

        # the reach bound, from a random twist
        y0 = np.array([*t.state[:3], *rng.normal(0.0, 0.3, 3)])
        _reach_holds(law, t, y0, window, steps, np.zeros(2), f"trial {k}")

        # the reach bound over long windows from fast twists (where a bound that grows with time is far off), and
        # for a law relative to its wheels (FrictionLaw.galilean) seen from a frame moving with them too
        more = np.random.default_rng([seed, k])  # its own draws: the trials above stay what they were
        y0 = np.array([*t.state[:3], *more.normal(0.0, 1.0, 3)])
        _reach_holds(law, t, y0, more.uniform(1.0, 3.0), 2 * steps, np.zeros(2), f"trial {k}, long window")
        if law.galilean:
            frame = more.uniform(-2.0, 2.0, 2)
            carried = copy.copy(t)
            carried.V = t.V + frame  # every wheel's velocity plus the frame's
            y0 = np.array([*t.state[:3], *(frame + more.normal(0.0, 0.3, 2)), more.normal(0.0, 0.3)])
            _reach_holds(law, carried, y0, more.uniform(0.2, 2.0), 2 * steps, frame,
                         f"trial {k}, in a frame moving at {frame} m/s")
        if law.frame_power(1.0, 1.0) is not None:
            _turning_reach_holds(law, t, np.random.default_rng([seed, k, 1]), steps, f"trial {k}, turning", 0.05,
                                 0.3)
            _turning_reach_holds(law, t, np.random.default_rng([seed, k, 2]), steps,
                                 f"trial {k}, riding a turning frame on wheels off it", 0.3, 0.0)

        # an event-driven law's constants and row
        if law.time_stepper is None:
            com = P.mean(axis=0)  # inside the supports' hull
            sol = solve_support(P, com, t.weight)
            N = sol.forces(com)
            y = np.array([*com, *y[2:]])
            want = law.wrench(P, N, t.V, t.U, mu, y)
            kc = law.constants(sol, t.V, t.U, mu)
            xi = com - sol.origin
            got = [*kc.force(xi, y[3:5], y[5]), kc.torque(xi, y[3:5], y[5])]
            assert np.allclose(got, want, rtol=1e-9, atol=tol), f"trial {k}: constants give {got}, cells {want}"
            kr, row = law.constants_and_row(sol, t.V, t.U, mu, t.mass, t.inertia)
            de = kr.d + kr.e
            expect = {"origin_x": sol.origin[0], "origin_y": sol.origin[1], "a_xx": kr.a[0, 0], "a_xy": kr.a[0, 1],
                      "a_yx": kr.a[1, 0], "a_yy": kr.a[1, 1], "b_x": kr.b[0], "b_y": kr.b[1], "c_xx": kr.c[0, 0],
                      "c_xy": kr.c[0, 1], "c_yx": kr.c[1, 0], "c_yy": kr.c[1, 1], "de_x": de[0], "de_y": de[1],
                      "f": kr.f, "damping": kr.damping, "weight": kr.weight, "moment_lin_xx": kr.moment_lin[0, 0],
                      "moment_lin_xy": kr.moment_lin[0, 1], "moment_lin_yx": kr.moment_lin[1, 0],
                      "moment_lin_yy": kr.moment_lin[1, 1], "moment_const_x": kr.moment_const[0],
                      "moment_const_y": kr.moment_const[1], "second_lin_x": kr.second_lin[0],
                      "second_lin_y": kr.second_lin[1], "second_const": kr.second_const, "inv_mass": 1.0 / t.mass,
                      "inv_inertia": 1.0 / t.inertia}
            assert len(row) == len(affine.ROW_FIELDS) and all(
                np.isclose(value, expect[name], rtol=1e-12, atol=1e-12 * scale)
                for name, value in zip(affine.ROW_FIELDS, row)), f"trial {k}: the row is not its constants'"
            assert np.allclose([*kr.force(xi, y[3:5], y[5]), kr.torque(xi, y[3:5], y[5])], want, rtol=1e-9,
                               atol=tol), f"trial {k}: constants_and_row's constants differ from the cells' wrench"


__all__ = ["FrictionLaw", "StepperOptions", "FrictionConstants", "CoulombLaw", "ViscousLaw", "StickSlipLaw", "LAWS",
           "law_named", "check_law", "rotating_reach", "coulomb_constants", "viscous_constants", "drive_constants",
           "J"]
