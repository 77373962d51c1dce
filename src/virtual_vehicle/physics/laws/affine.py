"""The affine piece constants shared by the laws whose wrench is affine in the parcel's state on one support set
(Coulomb, viscous): the paper's a, b, c, d, e, f (eqs. 23 and 29) and the damping moments (eqs. 33 and 38).

Units: N, N m, m, m/s, rad/s. Torques are about the vertical axis through the parcel's centre of mass,
counter-clockwise positive.

For one set of supports the wrench is

    f   = a X_c + b                                   (2-vector)
    tau = X_c^T c X_c + (d + e) . X_c + f_            (scalar)

plus, for a law with damping ``mu`` (s/m), ``-mu W Xdot_c`` (eq. 33) and ``-mu omega sum N_i |X_i - X_c|^2``
(eq. 38). The event-driven engine takes a piece's constants as one row of floats, :data:`ROW_FIELDS`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from virtual_vehicle.model.layout import collinear

J = np.array([[0.0, 1.0], [-1.0, 0.0]])
"""The paper's rotation matrix J (eq. 25): ``x^T J v`` is the scalar cross product ``x x v``."""

ROW_FIELDS = ("origin_x", "origin_y", "a_xx", "a_xy", "a_yx", "a_yy", "b_x", "b_y", "c_xx", "c_xy", "c_yx", "c_yy",
              "de_x", "de_y", "f", "damping", "weight", "moment_lin_xx", "moment_lin_xy", "moment_lin_yx",
              "moment_lin_yy", "moment_const_x", "moment_const_y", "second_lin_x", "second_lin_y", "second_const",
              "inv_mass", "inv_inertia")
"""The engine's contract with an event-driven law: the names, in order, of a piece's constants row
(:func:`~virtual_vehicle.engine.dynamics.constants_row`, read by :func:`~virtual_vehicle.engine._kernel.accelerations`):
the local origin (m), eqs. 23 and 29's constants (``de`` is ``d + e``), the damping (s/m) and weight (N), the moments
of eqs. 33 and 38, then 1 / mass (1/kg) and 1 / inertia (1/(kg m^2))."""

ROW_LENGTH = len(ROW_FIELDS)
"""How many floats a piece's constants row holds."""


def _place(name: str) -> int:
    """Where field ``name`` of :data:`ROW_FIELDS` sits in a row."""
    return ROW_FIELDS.index(name)


# Each field's place in a row, by its name in ROW_FIELDS: module-level integers, so that compiled code (the row's
# writer, row(), and its reader, the engine's accelerations) indexes with constants, and the order is ROW_FIELDS'.
R_ORIGIN_X, R_ORIGIN_Y = _place("origin_x"), _place("origin_y")
R_A_XX, R_A_XY, R_A_YX, R_A_YY = _place("a_xx"), _place("a_xy"), _place("a_yx"), _place("a_yy")
R_B_X, R_B_Y = _place("b_x"), _place("b_y")
R_C_XX, R_C_XY, R_C_YX, R_C_YY = _place("c_xx"), _place("c_xy"), _place("c_yx"), _place("c_yy")
R_DE_X, R_DE_Y, R_F = _place("de_x"), _place("de_y"), _place("f")
R_DAMPING, R_WEIGHT = _place("damping"), _place("weight")
R_MOMENT_LIN_XX, R_MOMENT_LIN_XY = _place("moment_lin_xx"), _place("moment_lin_xy")
R_MOMENT_LIN_YX, R_MOMENT_LIN_YY = _place("moment_lin_yx"), _place("moment_lin_yy")
R_MOMENT_CONST_X, R_MOMENT_CONST_Y = _place("moment_const_x"), _place("moment_const_y")
R_SECOND_LIN_X, R_SECOND_LIN_Y, R_SECOND_CONST = _place("second_lin_x"), _place("second_lin_y"), _place("second_const")
R_INV_MASS, R_INV_INERTIA = _place("inv_mass"), _place("inv_inertia")

_TERMS = 24
"""How many floats the packed terms hold ahead of the row in :func:`_terms_and_row`'s output."""


class FrictionConstants:
    """Per-support-set constants of the paper (eqs. 23, 29; 33, 38), in the frame of the points they came from,
    read as views of one packed array (a new piece's engine needs only its row, so its constants are not unpacked
    into twelve arrays until read).

    Attributes:
        a: (2, 2), b: (2,): net driving force ``a @ X_c + b`` (N).
        c: (2, 2), d: (2,), e: (2,), f: float: driving torque ``X_c @ c @ X_c + (d + e) @ X_c + f`` (N m).
        damping: viscous coefficient ``mu`` (s/m) for the damping terms of eqs. 33 and 38; 0 without damping.
        weight: W, N.
        moment_lin, moment_const: ``sum_i N_i X_i = moment_lin @ X_c + moment_const`` (N m). Equals ``W X_c`` when
            the supports are not collinear (eqs. 4, 5); differs for a laterally held parcel on a row.
        second_lin, second_const: ``sum_i N_i |X_i|^2 = second_lin @ X_c + second_const`` (N m^2), the paper's
            ``X^2 N`` of eq. 37.
    """

    __slots__ = ("terms", "damping", "weight")

    def __init__(self, terms: np.ndarray, damping: float, weight: float):
        """``terms``: the 24 packed floats of :func:`pack_terms` (a, b, c, d, e, f, moment_lin, moment_const,
        second_lin, second_const, arrays row-major); ``damping`` s/m; ``weight`` N."""
        self.terms = terms
        self.damping = float(damping)
        self.weight = float(weight)

    a = property(lambda self: self.terms[0:4].reshape(2, 2), doc="(2, 2) force per m of centre of mass, N/m (eq. 23).")
    b = property(lambda self: self.terms[4:6], doc="(2,) force at the local origin, N (eq. 23).")
    c = property(lambda self: self.terms[6:10].reshape(2, 2), doc="(2, 2) quadratic torque term, N/m (eq. 28).")
    d = property(lambda self: self.terms[10:12], doc="(2,) linear torque term from b, N (eq. 28).")
    e = property(lambda self: self.terms[12:14], doc="(2,) linear torque term from the cells' levers, N (eq. 28).")
    f = property(lambda self: float(self.terms[14]), doc="Torque at the local origin, N m (eq. 28).")
    moment_lin = property(lambda self: self.terms[15:19].reshape(2, 2),
                          doc="(2, 2) ``sum_i N_i X_i`` per m of centre of mass, N.")
    moment_const = property(lambda self: self.terms[19:21], doc="(2,) ``sum_i N_i X_i`` at the origin, N m.")
    second_lin = property(lambda self: self.terms[21:23],
                          doc="(2,) ``sum_i N_i |X_i|^2`` per m of centre of mass, N m (eq. 37).")
    second_const = property(lambda self: float(self.terms[23]),
                            doc="``sum_i N_i |X_i|^2`` at the origin, N m^2 (eq. 37).")

    def __getstate__(self):
        return self.terms, self.damping, self.weight

    def __setstate__(self, state):
        self.terms, self.damping, self.weight = state

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


def f64(a) -> np.ndarray:
    """``a`` as a contiguous float64 array (no copy when it is one), as the compiled sums take it."""
    return np.ascontiguousarray(a, dtype=np.float64)


def drive_constants(points, drive, force_lin, force_const, weight: float, mu: float,
                    damping: float = 0.0) -> FrictionConstants:
    """Constants for per-cell driving vectors ``drive`` ((m, 2)) and the affine normal-force map
    ``N = force_lin @ X_c + force_const`` over the cells at ``points`` ((m, 2), m), all in one frame.

    The driving force of cell i is ``mu N_i drive_i``: ``drive`` is the paper's F (Coulomb) or V (viscous).
    """
    P, D, G, h = (f64(v) for v in (points, drive, force_lin, force_const))
    return FrictionConstants(pack_terms(*_drive_terms(P, D, G, h, float(mu))), damping, weight)


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
def pack_terms(a, b, c, d, e, f, moment_lin, moment_const, second_lin, second_const):
    """The ten constants of :func:`_drive_terms` as the 24 floats :class:`FrictionConstants` reads."""
    out = np.empty(_TERMS)
    out[0:4], out[4:6], out[6:10], out[10:12], out[12:14], out[14] = a.ravel(), b, c.ravel(), d, e, f
    out[15:19], out[19:21], out[21:23], out[23] = moment_lin.ravel(), moment_const, second_lin, second_const
    return out


@njit(cache=True)
def row(a, b, c, d, e, f, damping, weight, moment_lin, moment_const, second_lin, second_const, origin, inv_mass,
        inv_inertia):
    """A piece's constants as one array, in the order of :data:`ROW_FIELDS` (each written at its ``R_`` place)."""
    out = np.empty(ROW_LENGTH)
    out[R_ORIGIN_X], out[R_ORIGIN_Y] = origin[0], origin[1]
    out[R_A_XX], out[R_A_XY], out[R_A_YX], out[R_A_YY] = a[0, 0], a[0, 1], a[1, 0], a[1, 1]
    out[R_B_X], out[R_B_Y] = b[0], b[1]
    out[R_C_XX], out[R_C_XY], out[R_C_YX], out[R_C_YY] = c[0, 0], c[0, 1], c[1, 0], c[1, 1]
    out[R_DE_X], out[R_DE_Y], out[R_F] = d[0] + e[0], d[1] + e[1], f
    out[R_DAMPING], out[R_WEIGHT] = damping, weight
    out[R_MOMENT_LIN_XX], out[R_MOMENT_LIN_XY] = moment_lin[0, 0], moment_lin[0, 1]
    out[R_MOMENT_LIN_YX], out[R_MOMENT_LIN_YY] = moment_lin[1, 0], moment_lin[1, 1]
    out[R_MOMENT_CONST_X], out[R_MOMENT_CONST_Y] = moment_const[0], moment_const[1]
    out[R_SECOND_LIN_X], out[R_SECOND_LIN_Y], out[R_SECOND_CONST] = second_lin[0], second_lin[1], second_const
    out[R_INV_MASS], out[R_INV_INERTIA] = inv_mass, inv_inertia
    return out


@njit(cache=True)
def _terms_and_row(P, D, G, h, mu, damping, weight, origin, inv_mass, inv_inertia):
    """:func:`_drive_terms` and the row of the piece they make (:func:`row`), in one compiled call, packed into one
    array (handing back eleven objects took ~3.5 us of a ~5 us call): the terms as :func:`pack_terms` packs them,
    then the row."""
    a, b, c, d, e, f, moment_lin, moment_const, second_lin, second_const = _drive_terms(P, D, G, h, mu)
    r = row(a, b, c, d, e, f, damping, weight, moment_lin, moment_const, second_lin, second_const, origin,
            inv_mass, inv_inertia)
    out = np.empty(_TERMS + r.shape[0])
    out[:_TERMS] = pack_terms(a, b, c, d, e, f, moment_lin, moment_const, second_lin, second_const)
    out[_TERMS:] = r
    return out


def constants_and_row(P, D, G, h, mu: float, damping: float, weight: float, origin, mass: float,
                      inertia: float) -> tuple[FrictionConstants, tuple[float, ...]]:
    """The constants of drive vectors ``D`` over supports ``P`` with normal-force map ``G``, ``h`` (contiguous
    float64 arrays) and the piece's row (:data:`ROW_FIELDS`) for a parcel of ``mass`` (kg) and ``inertia``
    (kg m^2), in one compiled call (a new piece needs both)."""
    out = _terms_and_row(P, D, G, h, float(mu), float(damping), float(weight), origin, 1.0 / mass, 1.0 / inertia)
    return FrictionConstants(out[:_TERMS], damping, weight), tuple(out[_TERMS:].tolist())


def cell_wrench(points, forces, com) -> tuple[float, float, float]:
    """Sum of per-cell horizontal forces (m, 2) applied at ``points`` and their torque about ``com`` (eq. 24)."""
    r = np.asarray(points, dtype=float) - np.asarray(com, dtype=float)
    F = forces.sum(axis=0)
    tau = float(np.sum(r[:, 0] * forces[:, 1] - r[:, 1] * forces[:, 0]))
    return float(F[0]), float(F[1]), tau


def all_in_contact_map(points, weight: float):
    """The paper's eq. 19 with every listed cell in contact (no lift-off), in the points' own frame."""
    P = np.asarray(points, dtype=float)
    if collinear(P):
        raise ValueError("the paper's planar constants need at least three non-collinear points")
    B = np.column_stack([np.ones(len(P)), P])
    minv = np.linalg.inv(B.T @ B)
    return B @ (weight * minv[:, 1:]), B @ (weight * minv[:, 0])
