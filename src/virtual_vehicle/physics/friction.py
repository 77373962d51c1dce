"""Friction laws: from normal forces and wheel velocities to the net horizontal force and torque on a parcel.

Units: N, N m, m, m/s, rad/s. Torques are about the vertical axis through the parcel's centre of mass,
counter-clockwise positive.

Both laws of the paper reduce, for one set of supports, to a few constants (eqs. 23 and 29):

    f   = a X_c + b                                   (2-vector)
    tau = X_c^T c X_c + (d + e) . X_c + f_            (scalar)

Coulomb (paper 4.3, eqs. 20-29): each wheel pushes with ``mu N_i`` in the direction it spins, so cell i pushes with
``mu N_i F_i`` where ``F_i = sum_k sign(V_i . u_k) u_k`` over its two wheels (``F_i = [+-1, +-1]`` for wheels
along x and y, eq. 21). As in the paper the wheels are assumed to slide under the parcel in their direction of
spin (the parcel is slower than the wheels); the simulator reports when that assumption fails.

Viscous (paper 4.4, eqs. 30-38): ``f_i = mu N_i (V_i - Xdot_c + omega J (X_i - X_c))`` with
``J = [[0, 1], [-1, 0]]``; the driving part has the Coulomb form with ``F`` replaced by the wheel velocities ``V``,
plus translational damping ``-mu W Xdot_c`` (eq. 33) and rotational damping ``-mu omega sum N_i |X_i - X_c|^2``
(eq. 38). Here ``mu`` is in s/m.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Protocol

import numpy as np
from numba import njit

from virtual_vehicle.model.layout import collinear
from virtual_vehicle.physics.contact import SupportSolution

J = np.array([[0.0, 1.0], [-1.0, 0.0]])
"""The paper's rotation matrix J (eq. 25): ``x^T J v`` is the scalar cross product ``x x v``."""


@dataclass(frozen=True, eq=False)
class FrictionConstants:
    """Per-support-set constants of the paper (eqs. 23, 29; 33, 38), in the frame of the points they came from.

    Attributes:
        a: (2, 2), b: (2,): net driving force ``a @ X_c + b`` (N).
        c: (2, 2), d: (2,), e: (2,), f: float: driving torque ``X_c @ c @ X_c + (d + e) @ X_c + f`` (N m).
        damping: viscous coefficient ``mu`` (s/m) for the damping terms of eqs. 33 and 38; 0 for Coulomb.
        weight: W, N.
        moment_lin, moment_const: ``sum_i N_i X_i = moment_lin @ X_c + moment_const`` (N m). Equals ``W X_c`` when
            the supports are not collinear (eqs. 4, 5); differs for a laterally held parcel on a row.
        second_lin, second_const: ``sum_i N_i |X_i|^2 = second_lin @ X_c + second_const`` (N m^2), the paper's
            ``X^2 N`` of eq. 37.
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    d: np.ndarray
    e: np.ndarray
    f: float
    damping: float
    weight: float
    moment_lin: np.ndarray
    moment_const: np.ndarray
    second_lin: np.ndarray
    second_const: float

    def force(self, com, velocity=(0.0, 0.0), omega: float = 0.0) -> np.ndarray:
        """Net horizontal force (N) for centre of mass ``com`` (m), its velocity (m/s) and spin ``omega`` (rad/s)."""
        X = np.asarray(com, dtype=float)
        v = np.asarray(velocity, dtype=float)
        f = self.a @ X + self.b
        if self.damping:
            D = self.moment_lin @ X + self.moment_const - self.weight * X  # sum N_i (X_i - X_c), zero in 2-D
            f = f + self.damping * (-self.weight * v + omega * (J @ D))  # eq. 32
        return f

    def torque(self, com, velocity=(0.0, 0.0), omega: float = 0.0) -> float:
        """Net torque (N m) about the centre of mass, eqs. 29 and 38."""
        X = np.asarray(com, dtype=float)
        v = np.asarray(velocity, dtype=float)
        tau = float(X @ self.c @ X + (self.d + self.e) @ X + self.f)  # eq. 29
        if self.damping:
            S1 = self.moment_lin @ X + self.moment_const
            S2 = float(self.second_lin @ X + self.second_const)
            D = S1 - self.weight * X
            second = S2 - 2.0 * float(X @ S1) + self.weight * float(X @ X)  # sum N_i |X_i - X_c|^2, eq. 37-38
            tau -= self.damping * (float(D[0] * v[1] - D[1] * v[0]) + omega * second)
        return tau

    @classmethod
    def _packed(cls, terms: np.ndarray, damping: float, weight: float) -> "FrictionConstants":
        """Constants whose arrays are read out of ``terms`` (:func:`_terms_and_row`'s packing) when one of them is
        first asked for: a new piece's engine needs only its row, and making the twelve fields took ~3 us of the
        ~9 us a new piece's constants cost."""
        new = object.__new__(cls)
        new.__dict__.update(_terms=terms, damping=float(damping), weight=float(weight))
        return new

    def __getattr__(self, name: str):
        """A field of constants made by :meth:`_packed` not yet read out of their packing (called only for names
        that are not in the instance's dict)."""
        terms = self.__dict__.get("_terms")
        if terms is None or name not in _PACKED_FIELDS:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        self.__dict__.update(_terms_fields(terms))
        return self.__dict__[name]


_PACKED_FIELDS = frozenset(f.name for f in fields(FrictionConstants)) - {"damping", "weight"}
"""The fields :meth:`FrictionConstants._packed` leaves in their packing until asked for (:func:`_terms_fields`)."""


def _f64(a) -> np.ndarray:
    """``a`` as a contiguous float64 array (no copy when it is one), as the compiled sums take it."""
    return np.ascontiguousarray(a, dtype=np.float64)


def drive_constants(points, drive, force_lin, force_const, weight: float, mu: float, damping: float = 0.0) -> FrictionConstants:
    """Constants for per-cell driving vectors ``drive`` ((m, 2)) and the affine normal-force map
    ``N = force_lin @ X_c + force_const`` over the cells at ``points`` ((m, 2), m), all in one frame.

    The driving force of cell i is ``mu N_i drive_i``: ``drive`` is the paper's F (Coulomb) or V (viscous).
    """
    P, D, G, h = (_f64(v) for v in (points, drive, force_lin, force_const))
    a, b, c, d, e, f, moment_lin, moment_const, second_lin, second_const = _drive_terms(P, D, G, h, float(mu))
    return FrictionConstants(a, b, c, d, e, f, float(damping), float(weight), moment_lin, moment_const, second_lin,
                             second_const)


@njit(cache=True)
def _drive_terms(P, D, G, h, mu):
    """The sums of :func:`drive_constants`, compiled (a new piece needs them; numpy took ~25 us in small calls)."""
    a, b, e, f = np.zeros((2, 2)), np.zeros(2), np.zeros(2), 0.0
    moment_lin, moment_const, second_lin, second_const = np.zeros((2, 2)), np.zeros(2), np.zeros(2), 0.0
    for i in range(P.shape[0]):
        R = mu * (P[i, 0] * D[i, 1] - P[i, 1] * D[i, 0])  # eq. 25: R_i = x_i F_yi - y_i F_xi
        sq = P[i, 0] * P[i, 0] + P[i, 1] * P[i, 1]
        for r in range(2):
            b[r] += mu * D[i, r] * h[i]  # eq. 23: b = mu F C M (M^T A M)^-1 M^T W_c
            e[r] += R * G[i, r]  # eq. 28, term post-multiplied by X_c
            moment_const[r] += P[i, r] * h[i]
            second_lin[r] += sq * G[i, r]
            for k in range(2):
                a[r, k] += mu * D[i, r] * G[i, k]  # eq. 23: a = mu F C M (M^T A M)^-1 M^T W_x
                moment_lin[r, k] += P[i, r] * G[i, k]
        f += R * h[i]  # eq. 28, constant term
        second_const += sq * h[i]
    c = np.empty((2, 2))  # eq. 28, term pre- and post-multiplied by X_c: c = -J a
    c[0], c[1] = -a[1], a[0]
    d = np.array([-b[1], b[0]])  # eq. 28, term pre-multiplied by X_c^T: d = -J b
    return a, b, c, d, e, f, moment_lin, moment_const, second_lin, second_const


@njit(cache=True)
def _row(a, b, c, d, e, f, damping, weight, moment_lin, moment_const, second_lin, second_const, origin, inv_mass,
         inv_inertia):
    """A piece's constants as one array, in the order :func:`~virtual_vehicle.engine._kernel.accelerations` takes them
    (documented at :func:`~virtual_vehicle.engine.dynamics.constants_row`, which calls this)."""
    return np.array([origin[0], origin[1], a[0, 0], a[0, 1], a[1, 0], a[1, 1], b[0], b[1],
                     c[0, 0], c[0, 1], c[1, 0], c[1, 1], d[0] + e[0], d[1] + e[1], f, damping, weight,
                     moment_lin[0, 0], moment_lin[0, 1], moment_lin[1, 0], moment_lin[1, 1],
                     moment_const[0], moment_const[1], second_lin[0], second_lin[1], second_const,
                     inv_mass, inv_inertia])


@njit(cache=True)
def _terms_and_row(P, D, G, h, mu, damping, weight, origin, inv_mass, inv_inertia):
    """:func:`_drive_terms` and the row of the piece they make (:func:`_row`), in one compiled call, packed into one
    array (handing back eleven objects took ~3.5 us of a ~5 us call): the terms as :func:`_unpack_terms` reads them,
    then the row."""
    a, b, c, d, e, f, moment_lin, moment_const, second_lin, second_const = _drive_terms(P, D, G, h, mu)
    row = _row(a, b, c, d, e, f, damping, weight, moment_lin, moment_const, second_lin, second_const, origin,
               inv_mass, inv_inertia)
    out = np.empty(24 + row.shape[0])
    out[0:4], out[4:6], out[6:10], out[10:12], out[12:14], out[14] = a.ravel(), b, c.ravel(), d, e, f
    out[15:19], out[19:21], out[21:23], out[23] = moment_lin.ravel(), moment_const, second_lin, second_const
    out[24:] = row
    return out


@njit(cache=True)
def _coulomb_terms_and_row(V, U, P, G, h, mu, weight, origin, inv_mass, inv_inertia):
    """:func:`_terms_and_row` of the Coulomb drive vectors of velocities ``V`` and directions ``U`` (eq. 21)."""
    return _terms_and_row(P, _coulomb_drive(V, U), G, h, mu, 0.0, weight, origin, inv_mass, inv_inertia)


def _unpack_terms(out, damping: float, weight: float) -> tuple[FrictionConstants, tuple[float, ...]]:
    """The :class:`FrictionConstants` (read out of ``out`` when first asked for, its arrays views of it) and the row
    from :func:`_terms_and_row`."""
    return FrictionConstants._packed(out, damping, weight), tuple(out[24:].tolist())


def _terms_fields(out) -> dict:
    """The fields of :class:`FrictionConstants` other than ``damping`` and ``weight`` from :func:`_terms_and_row`'s
    packing ``out`` (views of it)."""
    return {"a": out[0:4].reshape(2, 2), "b": out[4:6], "c": out[6:10].reshape(2, 2), "d": out[10:12],
            "e": out[12:14], "f": float(out[14]), "moment_lin": out[15:19].reshape(2, 2), "moment_const": out[19:21],
            "second_lin": out[21:23], "second_const": float(out[23])}


def _solution_arrays(solution):
    """The supports and normal-force map of a solved support set, as the compiled sums take them."""
    return solution.points, solution.force_lin, solution.force_const


@njit(cache=True)
def _coulomb_drive(V, U):
    """:meth:`CoulombLaw.drive_vectors` for velocities ``V`` (m, 2) and drive directions ``U`` (m, k, 2), compiled
    (each new piece needs them; two einsums took ~5 us)."""
    F = np.zeros((V.shape[0], 2))
    for i in range(V.shape[0]):
        for k in range(U.shape[1]):
            spin = np.sign(V[i, 0] * U[i, k, 0] + V[i, 1] * U[i, k, 1])  # eq. 21: the wheel's direction of spin
            F[i, 0] += spin * U[i, k, 0]
            F[i, 1] += spin * U[i, k, 1]
    return F


def _all_in_contact_map(points, weight: float):
    """The paper's eq. 19 with every listed cell in contact (no lift-off), in the points' own frame."""
    P = np.asarray(points, dtype=float)
    if collinear(P):
        raise ValueError("the paper's planar constants need at least three non-collinear points")
    B = np.column_stack([np.ones(len(P)), P])
    minv = np.linalg.inv(B.T @ B)
    return B @ (weight * minv[:, 1:]), B @ (weight * minv[:, 0])


def coulomb_constants(points, directions, weight: float, mu: float) -> FrictionConstants:
    """The paper's Coulomb constants a, b, c, d, e, f (eqs. 20-29) for cells at ``points`` ((m, 2), m) pushing in
    ``directions`` ((m, 2), the per-cell F of eq. 21), a parcel of weight ``weight`` (N) and friction coefficient
    ``mu``, all cells in contact. Coordinates are those of ``points``.

    >>> d = 0.1
    >>> k = coulomb_constants([[-d/2, -d/2], [d/2, -d/2], [-d/2, d/2], [d/2, d/2]],
    ...                       [[1, 1], [-1, 1], [1, -1], [-1, -1]], weight=10.0, mu=0.5)
    >>> k.a.round(9).tolist(), k.b.round(9).tolist(), abs(k.f) < 1e-12
    ([[-100.0, 0.0], [0.0, -100.0]], [0.0, 0.0], True)
    """
    G, h = _all_in_contact_map(points, weight)
    return drive_constants(points, directions, G, h, weight, mu)


def viscous_constants(points, velocities, weight: float, mu: float) -> FrictionConstants:
    """The viscous constants (eqs. 30-38) for wheel velocities ``velocities`` ((m, 2), m/s) at ``points`` (m),
    all cells in contact; ``mu`` in s/m."""
    G, h = _all_in_contact_map(points, weight)
    return drive_constants(points, velocities, G, h, weight, mu, damping=mu)


class FrictionLaw(Protocol):
    """A friction law: turns supports, normal forces and wheel velocities into constants and wrenches."""

    name: str

    def drive_vectors(self, velocities: np.ndarray, drive_directions: np.ndarray) -> np.ndarray:
        """(n, 2) the per-cell drive vector the law's constants are built from (eq. 21 for Coulomb, the V_i of eq. 30
        for viscous), from cell velocities (n, 2) m/s and drive directions (n, 2, 2)."""

    def constants(self, solution: SupportSolution, velocities: np.ndarray, drive_directions: np.ndarray,
                  mu: float) -> FrictionConstants:
        """The per-support-set constants (eqs. 20-29 Coulomb, 30-38 viscous) of a solved support set: the parcel's
        wrench is then affine in its state."""

    def constants_and_row(self, solution: SupportSolution, velocities: np.ndarray, drive_directions: np.ndarray,
                          mu: float, mass: float, inertia: float) -> tuple[FrictionConstants, tuple[float, ...]]:
        """:meth:`constants` and the piece's constants row (:func:`~virtual_vehicle.engine.dynamics.constants_row`) for a
        parcel of ``mass`` (kg) and ``inertia`` (kg m^2), in one compiled call (a new piece needs both)."""

    def wrench(self, points, normal, velocities, drive_directions, mu: float, state) -> tuple[float, float, float]:
        """The net horizontal force (N, N) and torque (N m) on the parcel by direct summation over the cells at
        ``points`` with normal forces ``normal`` (N); ``state`` = (x, y, theta, vx, vy, omega)."""


def _cell_wrench(points, forces, com) -> tuple[float, float, float]:
    """Sum of per-cell horizontal forces (m, 2) applied at ``points`` and their torque about ``com`` (eq. 24)."""
    r = np.asarray(points, dtype=float) - np.asarray(com, dtype=float)
    F = forces.sum(axis=0)
    tau = float(np.sum(r[:, 0] * forces[:, 1] - r[:, 1] * forces[:, 0]))
    return float(F[0]), float(F[1]), tau


@dataclass(frozen=True)
class CoulombLaw:
    """The paper's Coulomb law (4.3): each wheel pushes with ``mu N_i`` along its drive direction, in the direction
    it spins; a stopped wheel pushes nothing. ``mu`` is dimensionless."""

    name: str = "coulomb"

    def drive_vectors(self, velocities, drive_directions) -> np.ndarray:
        """Per-cell F (eq. 21): ``sum_k sign(V_i . u_k) u_k``."""
        return _coulomb_drive(_f64(velocities), _f64(drive_directions))

    def constants(self, solution, velocities, drive_directions, mu) -> FrictionConstants:
        """Per-support-set constants (eqs. 20-29) from the drive vectors of eq. 21."""
        F = self.drive_vectors(velocities, drive_directions)
        return drive_constants(solution.points, F, solution.force_lin, solution.force_const, solution.weight, mu)

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        """See :meth:`FrictionLaw.constants_and_row`."""
        terms = _coulomb_terms_and_row(_f64(velocities), _f64(drive_directions), *_solution_arrays(solution),
                                       float(mu), float(solution.weight), solution.origin, 1.0 / mass, 1.0 / inertia)
        return _unpack_terms(terms, 0.0, solution.weight)

    def wrench(self, points, normal, velocities, drive_directions, mu, state):
        """Direct per-cell sum (eqs. 22, 24) for checking the constants; ``state`` = (x, y, theta, vx, vy, omega)."""
        F = self.drive_vectors(velocities, drive_directions)
        return _cell_wrench(points, mu * np.asarray(normal)[:, None] * F, state[:2])


@dataclass(frozen=True)
class ViscousLaw:
    """The paper's viscous law (4.4): force proportional to normal force and slip velocity; ``mu`` in s/m."""

    name: str = "viscous"

    def drive_vectors(self, velocities, drive_directions) -> np.ndarray:
        """Per-cell wheel velocity projected on the drive directions (the V_i of eq. 30), m/s:
        ``sum_k (V_i . u_k) u_k``."""
        return np.asarray(velocities, dtype=float)

    def constants(self, solution, velocities, drive_directions, mu) -> FrictionConstants:
        """Per-support-set constants (eqs. 30-38): the wrench is linear in the parcel's twist."""
        return drive_constants(solution.points, velocities, solution.force_lin, solution.force_const,
                               solution.weight, mu, damping=mu)

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        """See :meth:`FrictionLaw.constants_and_row`."""
        P, G, h = _solution_arrays(solution)
        terms = _terms_and_row(P, _f64(velocities), G, h, float(mu), float(mu), float(solution.weight),
                               solution.origin, 1.0 / mass, 1.0 / inertia)
        return _unpack_terms(terms, mu, solution.weight)

    def wrench(self, points, normal, velocities, drive_directions, mu, state):
        """Direct per-cell sum of eq. 30 and its torque (eq. 34)."""
        P = np.asarray(points, dtype=float)
        X = np.asarray(state[:2], dtype=float)
        v = np.asarray(state[3:5], dtype=float)
        slip = np.asarray(velocities, dtype=float) - v + state[5] * (P - X) @ J.T  # eq. 30
        return _cell_wrench(P, mu * np.asarray(normal)[:, None] * slip, X)


@dataclass(frozen=True)
class StickSlipLaw:
    """Stick-slip friction (paper Section 5): each wheel sticks to the parcel or slides, solved as a complementarity
    problem every time step (:mod:`virtual_vehicle.engine.stickslip`). The parcel's ``mu`` is the kinetic coefficient
    and
    ``mu_static`` (default ``mu``) the static one. Always time-stepped. Its per-support-set constants (for reference
    only) are those of the sliding regime: the paper's Coulomb constants. ``max_sweeps`` and ``tolerance`` (relative
    to the largest impulse bound) control the projected Gauss-Seidel solver."""

    name: str = "stick_slip"
    max_sweeps: int = 1000
    tolerance: float = 1e-12

    def drive_vectors(self, velocities, drive_directions) -> np.ndarray:
        """Per-cell wheel velocity projected on the drive directions, m/s (the slip velocities are formed from it)."""
        return CoulombLaw().drive_vectors(velocities, drive_directions)

    def constants(self, solution, velocities, drive_directions, mu) -> FrictionConstants:
        """Per-support-set geometry (the law's wrench is solved per step, not affine in the state)."""
        return CoulombLaw().constants(solution, velocities, drive_directions, mu)

    def constants_and_row(self, solution, velocities, drive_directions, mu, mass, inertia):
        """See :meth:`FrictionLaw.constants_and_row` (the sliding regime's, as :meth:`constants`)."""
        return CoulombLaw().constants_and_row(solution, velocities, drive_directions, mu, mass, inertia)

    def wrench(self, points, normal, velocities, drive_directions, mu, state):
        """The sliding-regime wrench (every wheel at its kinetic bound in its direction of spin)."""
        return CoulombLaw().wrench(points, normal, velocities, drive_directions, mu, state)


LAWS: dict[str, FrictionLaw] = {"coulomb": CoulombLaw(), "viscous": ViscousLaw(), "stick_slip": StickSlipLaw()}
"""Friction laws by name, as written in scenario files."""

__all__ = ["FrictionConstants", "CoulombLaw", "ViscousLaw", "StickSlipLaw", "LAWS", "coulomb_constants", "viscous_constants",
           "drive_constants", "J"]
