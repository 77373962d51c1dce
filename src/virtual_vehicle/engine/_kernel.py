"""The event engine's inner loop, compiled (numba): DOP853 steps on one smooth piece, event search and location.

Units: SI (m, s, kg, N, rad). State ``[x, y, theta, vx, vy, omega]``.

:func:`run_piece` integrates one piece (one support set and contact set, eqs. 23/29/33/38 as the constants row of
:func:`~virtual_vehicle.engine.dynamics.constants_row`) with scipy's DOP853 scheme (same tableau, error norm and
step-size rule as ``scipy.integrate.DOP853``; sums taken in plain loops, so results agree with scipy's to rounding, not
to the last bit), samples every step's dense output for the first sign change of an event value, locates it by Brent's
method and probes past it, as :mod:`virtual_vehicle.engine.dynamics` documents. In Python each of the ~100 support
changes a second of an oscillating Coulomb parcel cost about a millisecond, mostly in array calls on a handful of
numbers; compiled, a piece's own work takes a few tens of microseconds, and most of what remains is the Python between
pieces (which cells, the support solve, the friction constants). The piece (:func:`_piece`), its event search and
location are leaves (:data:`~virtual_vehicle.compiled.leaf`: no reference counting, nothing allocated) over one
:class:`SearchScratch` that :func:`run_events` makes per call; :func:`run_piece` wraps the piece for callers from Python.

Event values of a segment (:class:`~virtual_vehicle.engine.dynamics._Segment`), in order: the footprint margin of every
candidate cell (m), the spring force of every supporting cell (N), the slack of the centre of mass in the supports'
hull (m) and the distance left before the candidate list must be refreshed (m). A segment is passed as a
:class:`Segment`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.integrate import DOP853

from virtual_vehicle.compiled import leaf
from virtual_vehicle.model.parcel import _within
from virtual_vehicle.physics.contact import _MAX_ITER, SOLVED, solve_planar_kernel
from virtual_vehicle.physics.contact import _holds as _holds_packed
from virtual_vehicle.physics.laws.affine import _terms_and_row
from virtual_vehicle.physics.laws.coulomb import CoulombLaw
from virtual_vehicle.physics.laws.viscous import ViscousLaw

from virtual_vehicle.physics.laws.affine import (
    R_A_XX,
    R_A_XY,
    R_A_YX,
    R_A_YY,
    R_B_X,
    R_B_Y,
    R_C_XX,
    R_C_XY,
    R_C_YX,
    R_C_YY,
    R_DAMPING,
    R_DE_X,
    R_DE_Y,
    R_F,
    R_INV_INERTIA,
    R_INV_MASS,
    R_MOMENT_CONST_X,
    R_MOMENT_CONST_Y,
    R_MOMENT_LIN_XX,
    R_MOMENT_LIN_XY,
    R_MOMENT_LIN_YX,
    R_MOMENT_LIN_YY,
    R_ORIGIN_X,
    R_ORIGIN_Y,
    R_SECOND_CONST,
    R_SECOND_LIN_X,
    R_SECOND_LIN_Y,
    R_WEIGHT,
)
from virtual_vehicle.physics.stick_modes import _wheel_arrays, zonotope_grip

RECTANGLE, CONVEX, POLYGON = 0, 1, 2
"""Footprint kinds: margins in closed form, from half-planes, or as a signed distance to a simple polygon."""

# Outcomes of run_piece
REACHED, EVENT, PAUSED, FAILED, NOT_FINITE, NO_CONVERGENCE = 0, 1, 2, 3, 4, 5

SUBSAMPLES = 8
"""Points inside every step at which the event predicates are checked, so that two crossings in one long step are
told apart (intervals where a crossing could hide between samples are refined further)."""
RATE_SAFETY = 2.0
"""Factor on the acceleration bounds, which are taken from the two ends of a step (smooth within a piece)."""
MIN_BRACKET = 1e-9
"""Shortest interval (s) the search for a hidden crossing bisects to: a graze shallower than speed x 1e-9 s / 2
(about 1e-10 m at 0.2 m/s) is not resolved."""
PROBE_FIRST = 1e-9
"""First look-ahead (s) past a located event, to read the new piece where no value is within rounding noise of zero.
Two events closer than the look-ahead are taken as one (the integration itself restarts at the root)."""
PROBE_MAX = 1e-6
"""Longest time (s) past an event that the integrator looks ahead to see every value clear of rounding noise."""

# scipy's DOP853 tableau and step-size rule (scipy.integrate._ivp.rk)
_N_STAGES = DOP853.n_stages
_A, _B, _E3, _E5, _D, _A_EXTRA = (np.ascontiguousarray(a, dtype=np.float64)  # compiled in as constants
                                  for a in (DOP853.A, DOP853.B, DOP853.E3, DOP853.E5, DOP853.D, DOP853.A_EXTRA))
_N_EXTENDED = _D.shape[1]
_ERROR_EXPONENT = -1.0 / (DOP853.error_estimator_order + 1)
_SAFETY, _MIN_FACTOR, _MAX_FACTOR = 0.9, 0.2, 10.0


def accelerations(row, x, y, vx, vy, om):
    """Linear and angular acceleration (m/s^2, m/s^2, rad/s^2) at centre of mass (x, y) (m) moving at (vx, vy) (m/s)
    and spinning at ``om`` (rad/s), from a piece's :func:`~virtual_vehicle.engine.dynamics.constants_row`. Works on
    floats (one parcel) and on arrays (one entry per parcel, ``row`` a sequence of arrays), with the same arithmetic,
    and compiled (:data:`accelerations_compiled`). The row is read by field name (the ``R_`` places of
    :data:`~virtual_vehicle.physics.laws.affine.ROW_FIELDS`), which compiled code takes as constants when it is
    compiled: numba's cache knows only this file, so after reordering ROW_FIELDS clear the ``__pycache__`` (the
    compiled reading is tested against this one)."""
    ox, oy = row[R_ORIGIN_X], row[R_ORIGIN_Y]  # by name (ROW_FIELDS): constants to the compiled code
    a11, a12, a21, a22 = row[R_A_XX], row[R_A_XY], row[R_A_YX], row[R_A_YY]
    b1, b2 = row[R_B_X], row[R_B_Y]
    c11, c12, c21, c22 = row[R_C_XX], row[R_C_XY], row[R_C_YX], row[R_C_YY]
    e1, e2, f0 = row[R_DE_X], row[R_DE_Y], row[R_F]
    mu, W = row[R_DAMPING], row[R_WEIGHT]
    K11, K12, K21, K22 = row[R_MOMENT_LIN_XX], row[R_MOMENT_LIN_XY], row[R_MOMENT_LIN_YX], row[R_MOMENT_LIN_YY]
    k1, k2 = row[R_MOMENT_CONST_X], row[R_MOMENT_CONST_Y]
    s1, s2, s0 = row[R_SECOND_LIN_X], row[R_SECOND_LIN_Y], row[R_SECOND_CONST]
    inv_m, inv_i = row[R_INV_MASS], row[R_INV_INERTIA]
    X1 = x - ox
    X2 = y - oy
    fx = a11 * X1 + a12 * X2 + b1  # eq. 23
    fy = a21 * X1 + a22 * X2 + b2
    tau = X1 * (c11 * X1 + c12 * X2) + X2 * (c21 * X1 + c22 * X2) + e1 * X1 + e2 * X2 + f0  # eq. 29
    # Viscous damping (zero for Coulomb, mu = 0): sum N_i (X_i - X_c) is zero unless a row holds the parcel laterally
    S1x = K11 * X1 + K12 * X2 + k1
    S1y = K21 * X1 + K22 * X2 + k2
    Dx = S1x - W * X1
    Dy = S1y - W * X2
    fx = fx + mu * (-W * vx + om * Dy)  # eqs. 32-33
    fy = fy + mu * (-W * vy - om * Dx)
    second = (s1 * X1 + s2 * X2 + s0) - 2.0 * (X1 * S1x + X2 * S1y) + W * (X1 * X1 + X2 * X2)
    tau = tau - mu * ((Dx * vy - Dy * vx) + om * second)  # eq. 38
    return fx * inv_m, fy * inv_m, tau * inv_i


accelerations_compiled = leaf(accelerations)


@njit(cache=True)
def pattern(positions, support, unit):
    """Where the cells ``support`` of ``positions`` ((n, 2), m) lie: (their positions (m, 2), their centroid (2,),
    their offsets from the first of them in whole ``unit`` (m): the key of their geometric pattern, compared by the
    pattern cache of :mod:`virtual_vehicle.engine.dynamics`)."""
    m = support.shape[0]
    pts = np.empty((m, 2))
    origin = np.zeros(2)
    rel = np.empty((m, 2), np.int64)
    for i in range(m):
        for j in range(2):
            pts[i, j] = positions[support[i], j]
            origin[j] += pts[i, j]  # as numpy's mean over axis 0: row by row, then divided
            rel[i, j] = np.int64(np.rint((pts[i, j] - pts[0, j]) / unit))
    origin /= m
    return pts, origin, rel


class Segment(NamedTuple):
    """One segment's arrays, as the compiled functions take them (a numba named tuple). Lengths in m.

    ``kind`` is a footprint kind, with ``half`` (2,) the rectangle's half extents, ``normals`` (k, 2) and
    ``offsets`` (k,) a convex footprint's outward half-planes (also a rectangle's: the hidden-crossing test uses
    them), ``vertices`` (k, 2) a polygon's outline. ``candidates`` (nc, 2) are the cells near the parcel;
    ``origin`` .. ``hull_offsets`` the piece's support solution
    (:class:`~virtual_vehicle.physics.contact.SupportSolution`);
    ``center`` and ``buffer`` bound where the candidates cover the footprint; ``reach`` bounds a candidate's distance
    from the centre of mass while they do; ``noise_length`` (m) and ``noise_force`` (N) are the rounding noise of
    the lengths and of the spring forces among the event values (:func:`_noise`); ``spring_dirs``
    (m, 2) the gradients of the spring forces in the centre of mass (N/m) and ``spring_gradient`` (m,) their norms;
    ``ids`` (nc,) the candidates' cell ids.
    """

    kind: int
    convex: bool
    half: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    vertices: np.ndarray
    candidates: np.ndarray
    origin: np.ndarray
    basis: np.ndarray
    plane_lin: np.ndarray
    plane_const: np.ndarray
    hull_normals: np.ndarray
    hull_offsets: np.ndarray
    center: np.ndarray
    buffer: float
    reach: float
    noise_length: float
    noise_force: float
    spring_dirs: np.ndarray
    spring_gradient: np.ndarray
    ids: np.ndarray


def outline(spec) -> tuple:
    """The footprint of parcel ``spec`` (:class:`~virtual_vehicle.model.parcel.ParcelSpec`) as :class:`Segment` holds
    it: (kind, convex, half, normals, offsets, vertices), lengths in m."""
    def arr(a, shape):
        return np.ascontiguousarray(a, dtype=np.float64).reshape(shape)

    convex = bool(spec.convex)
    half = spec.half_extents
    normals, offsets = spec.halfplanes if convex else (np.zeros((0, 2)), np.zeros(0))
    kind = RECTANGLE if half is not None else CONVEX if convex else POLYGON
    return (kind, convex, arr(half if half is not None else (0.0, 0.0), 2), arr(normals, (-1, 2)), arr(offsets, -1),
            arr(spec.footprint, (-1, 2)))


def make_segment(footprint: tuple, radius: float, candidates: np.ndarray, sol, center: np.ndarray, buffer: float,
                 noise_length: float, noise_force: float, ids: np.ndarray) -> tuple:
    """The fields of the :class:`Segment` (in its order, as a plain tuple: numba types a plain tuple in compiled code, a
    named one in Python, ~1.5 us more a call; :func:`run_piece` names them again) of a parcel of footprint ``footprint``
    (its :func:`outline`) and ``radius`` (m) with candidate cells ``candidates`` ((nc, 2) float64, m) on support
    solution ``sol`` (whose arrays are float64 and contiguous, as :mod:`virtual_vehicle.physics.contact` makes them),
    its candidates gathered within ``radius + buffer`` of ``center`` (m), whose cell ids are ``ids`` ((nc,) int64);
    event values below ``noise_length`` (m) or ``noise_force`` (N) are rounding noise."""
    return (*footprint, candidates, sol.origin, sol.basis, sol.plane_lin, sol.plane_const, sol.hull_normals,
            sol.hull_offsets, center, float(buffer), float(radius + 2 * buffer), float(noise_length),
            float(noise_force), sol.spring_lin, sol.spring_gradient, ids)


@njit(cache=True, inline="always")  # called per candidate and sample: a call costs more than the margin
def _margin(kind, half, normals, offsets, v, bx, by):
    """Signed margin (m) of body-frame point (bx, by): positive inside (the distance to the nearest edge for a convex
    footprint), negative outside (the most violated edge's distance; for a polygon, minus the distance to it)."""
    if kind == RECTANGLE:
        return min(half[0] - abs(bx), half[1] - abs(by))
    if kind == CONVEX:
        m = np.inf
        for k in range(offsets.shape[0]):
            m = min(m, offsets[k] - (bx * normals[k, 0] + by * normals[k, 1]))
        return m
    # simple polygon (vertices v): distance to the boundary, signed by the even-odd rule
    nv = v.shape[0]
    d2 = np.inf
    inside = False
    for k in range(nv):
        ax, ay = v[k, 0], v[k, 1]
        cx, cy = v[(k + 1) % nv, 0], v[(k + 1) % nv, 1]
        ex, ey = cx - ax, cy - ay
        u = min(1.0, max(0.0, ((bx - ax) * ex + (by - ay) * ey) / (ex * ex + ey * ey)))
        px, py = ax + u * ex - bx, ay + u * ey - by
        d2 = min(d2, px * px + py * py)
        if (ay > by) != (cy > by) and bx < ax + (by - ay) * ex / ey:
            inside = not inside
    d = math.sqrt(d2)
    return d if inside else -d


@leaf
def n_values(seg):
    """How many event values segment ``seg`` has: a margin per candidate, a spring force per support, a slack per
    hull facet, and the refresh distance (:func:`values`' order)."""
    return seg.candidates.shape[0] + seg.basis.shape[0] + seg.hull_offsets.shape[0] + 1


@leaf
def values(seg, y, out):
    """Event values of segment ``seg`` at state ``y`` into ``out`` (n,)."""
    c, s = math.cos(y[2]), math.sin(y[2])
    cand, half, normals, offsets, vertices = seg.candidates, seg.half, seg.normals, seg.offsets, seg.vertices
    nc = cand.shape[0]
    # One loop per footprint kind, the kind a constant in each, so that the compiler drops the other kinds' code from
    # the loop: with the kind tested per candidate, the margins took ten times as long (0.6 against 0.06 us for 39).
    if seg.kind == RECTANGLE:
        for i in range(nc):
            out[i] = _candidate_margin(cand, RECTANGLE, half, normals, offsets, vertices, i, y, c, s)
    elif seg.kind == CONVEX:
        for i in range(nc):
            out[i] = _candidate_margin(cand, CONVEX, half, normals, offsets, vertices, i, y, c, s)
    else:
        for i in range(nc):
            out[i] = _candidate_margin(cand, POLYGON, half, normals, offsets, vertices, i, y, c, s)
    basis, plane_lin, plane_const = seg.basis, seg.plane_lin, seg.plane_const
    m = basis.shape[0]
    xi0, xi1 = y[0] - seg.origin[0], y[1] - seg.origin[1]
    if basis.shape[1] == 3:  # a plane's three coefficients once, not once a cell (as _spring sums them)
        p0 = plane_lin[0, 0] * xi0 + plane_lin[0, 1] * xi1 + plane_const[0]
        p1 = plane_lin[1, 0] * xi0 + plane_lin[1, 1] * xi1 + plane_const[1]
        p2 = plane_lin[2, 0] * xi0 + plane_lin[2, 1] * xi1 + plane_const[2]
        for k in range(m):
            out[nc + k] = ((0.0 + basis[k, 0] * p0) + basis[k, 1] * p1) + basis[k, 2] * p2
    else:
        for k in range(m):
            out[nc + k] = _spring(basis, plane_lin, plane_const, k, xi0, xi1)
    hull_normals, hull_offsets = seg.hull_normals, seg.hull_offsets
    q = hull_offsets.shape[0]
    for k in range(q):
        out[nc + m + k] = _slack(hull_normals, hull_offsets, k, xi0, xi1)
    out[nc + m + q] = _refresh(seg, y)


@leaf
def value(seg, y, i):
    """Event value ``i`` of segment ``seg`` at state ``y`` (as :func:`values` computes it, alone)."""
    nc, m, q = seg.candidates.shape[0], seg.basis.shape[0], seg.hull_offsets.shape[0]
    if i < nc:
        return _candidate_margin(seg.candidates, seg.kind, seg.half, seg.normals, seg.offsets, seg.vertices, i, y,
                                 math.cos(y[2]), math.sin(y[2]))
    xi0, xi1 = y[0] - seg.origin[0], y[1] - seg.origin[1]
    if i < nc + m:
        return _spring(seg.basis, seg.plane_lin, seg.plane_const, i - nc, xi0, xi1)
    if i < nc + m + q:
        return _slack(seg.hull_normals, seg.hull_offsets, i - nc - m, xi0, xi1)
    return _refresh(seg, y)


@njit(cache=True, inline="always")
def _candidate_margin(cand, kind, half, normals, offsets, vertices, i, y, c, s):
    """Footprint margin (m) of candidate cell ``i`` at state ``y`` with heading cosine and sine ``c``, ``s``."""
    dx = cand[i, 0] - y[0]
    dy = cand[i, 1] - y[1]
    return _margin(kind, half, normals, offsets, vertices, c * dx + s * dy, -s * dx + c * dy)  # world -> body


@njit(cache=True, inline="always")
def _spring(basis, plane_lin, plane_const, k, xi0, xi1):
    """Spring force (N) of supporting cell ``k`` at local centre of mass (xi0, xi1) (m)."""
    force = 0.0
    for j in range(basis.shape[1]):
        force += basis[k, j] * (plane_lin[j, 0] * xi0 + plane_lin[j, 1] * xi1 + plane_const[j])
    return force


@njit(cache=True, inline="always")
def _slack(hull_normals, hull_offsets, k, xi0, xi1):
    """Slack (m) of the local centre of mass (xi0, xi1) in hull half-plane ``k``."""
    return hull_offsets[k] - (xi0 * hull_normals[k, 0] + xi1 * hull_normals[k, 1])


@njit(cache=True, inline="always")
def _refresh(seg, y):
    """Distance (m) the centre of mass may still move before the candidates must be gathered again."""
    return seg.buffer - math.hypot(y[0] - seg.center[0], y[1] - seg.center[1])


@njit(cache=True)
def cell_margins(kind, half, normals, offsets, vertices, cells, y):
    """Footprint margins (m) of the cells at ``cells`` ((nc, 2), m) with the parcel at pose ``y`` (x, y, theta, ...),
    as the event values compute them; also the smallest ``|margin|`` (inf for no cell). The footprint is a
    :func:`outline`'s first five entries less ``convex``."""
    c, s = math.cos(y[2]), math.sin(y[2])
    nc = cells.shape[0]
    out = np.empty(nc)
    if kind == RECTANGLE:  # one loop per kind, as in values()
        for i in range(nc):
            out[i] = _candidate_margin(cells, RECTANGLE, half, normals, offsets, vertices, i, y, c, s)
    elif kind == CONVEX:
        for i in range(nc):
            out[i] = _candidate_margin(cells, CONVEX, half, normals, offsets, vertices, i, y, c, s)
    else:
        for i in range(nc):
            out[i] = _candidate_margin(cells, POLYGON, half, normals, offsets, vertices, i, y, c, s)
    smallest = np.inf
    for i in range(nc):
        smallest = min(smallest, abs(out[i]))
    return out, smallest


@njit(cache=True, inline="always")
def _room(value, gx, gy):
    """How far (m) the centre of mass can move before an affine function of it with ``value`` here (> 0 is clear) and
    gradient (gx, gy) reaches zero: inf for a constant one that is clear, -inf for one that is not."""
    norm = math.sqrt(gx * gx + gy * gy)
    if norm > 0:
        return value / norm
    return np.inf if value > 0 else -np.inf


@njit(cache=True)
def support_slack(basis, plane_lin, plane_const, spring_lin, hull_normals, hull_offsets, xi0, xi1, noise_force,
                  noise_length):
    """How far (m) the local centre of mass (xi0, xi1) (m) can move before any spring force (eq. 19, gradient rows
    ``spring_lin`` in N/m) or any supporting half-plane of a solution changes sign, each less its rounding noise
    (``noise_force`` in N; ``noise_length`` m per unit of a half-plane normal's length); inf when nothing bounds it."""
    out = np.inf
    for k in range(basis.shape[0]):
        force = abs(_spring(basis, plane_lin, plane_const, k, xi0, xi1)) - noise_force
        out = min(out, _room(force, spring_lin[k, 0], spring_lin[k, 1]))
    for k in range(hull_offsets.shape[0]):
        nx, ny = hull_normals[k, 0], hull_normals[k, 1]
        slack = _slack(hull_normals, hull_offsets, k, xi0, xi1) - noise_length * math.sqrt(nx * nx + ny * ny)
        out = min(out, _room(slack, nx, ny))
    return out


@njit(cache=True, inline="always")
def _noise(nc, m, noise_length, noise_force, i):
    """Rounding noise of event value ``i`` of a segment with ``nc`` candidates and ``m`` supports (see
    :class:`Segment`): below it its sign is not to be trusted."""
    return noise_force if nc <= i < nc + m else noise_length


@leaf
def _sign(v):
    return (v > 0) - (v < 0)


@leaf
def _edge_and_rate(normals, offsets, y, px, py):
    """For a convex footprint at state ``y``: point (px, py)'s nearest (most violated) edge and that edge distance's
    rate of change (m/s), from the point's velocity relative to the parcel in the body frame."""
    c, s = math.cos(y[2]), math.sin(y[2])
    dx, dy = px - y[0], py - y[1]
    bx, by = c * dx + s * dy, -s * dx + c * dy
    edge = 0
    best = np.inf
    for k in range(offsets.shape[0]):
        h = offsets[k] - (bx * normals[k, 0] + by * normals[k, 1])
        if h < best:
            best, edge = h, k
    om = y[5]
    wx, wy = -(y[3] - om * dy), -(y[4] + om * dx)  # cell velocity relative to the parcel point
    pbx, pby = c * wx + s * wy, -s * wx + c * wy
    return edge, -(normals[edge, 0] * pbx + normals[edge, 1] * pby)


@leaf
def may_hide(seg, ya, yb, ga, gb, dt, acc, spin_acc, out):
    """Which event values (into ``out``) could have crossed zero and come back between states ``ya`` and ``yb``,
    ``dt`` seconds apart, without changing sign at them, given bounds on the parcel's acceleration (m/s^2) and
    angular acceleration (rad/s^2). Returns whether any could.

    A footprint margin changes no faster than a body point at the candidates' distance moves, and for a convex
    footprint a cell can slip in and out unseen only by cutting a corner or if its edge distance turns around; a
    spring force is affine in the centre of mass, so it can dip through zero only if its rate ``G . v`` changes
    sign, which needs ``|G . v_a| + |G . v_b| <= |G| acc dt``. Hull slacks and the refresh distance are not
    searched (tipping shows up as a lift-off; a late refresh is harmless)."""
    cand, reach, dirs, grad = seg.candidates, seg.reach, seg.spring_dirs, seg.spring_gradient
    convex, normals, offsets, noise_length, noise_force = (seg.convex, seg.normals, seg.offsets, seg.noise_length,
                                                           seg.noise_force)
    nc, m = cand.shape[0], dirs.shape[0]
    speed = max(math.hypot(ya[3], ya[4]), math.hypot(yb[3], yb[4])) + acc * dt / 2
    spin = max(abs(ya[5]), abs(yb[5])) + spin_acc * dt / 2
    point_acc = acc + spin_acc * reach + spin * spin * reach
    any_hidden = False
    for i in range(out.shape[0]):
        out[i] = False
    for i in range(nc):
        if not abs(ga[i]) + abs(gb[i]) <= (speed + spin * reach) * dt:
            continue
        if convex:
            edge_a, rate_a = _edge_and_rate(normals, offsets, ya, cand[i, 0], cand[i, 1])
            edge_b, rate_b = _edge_and_rate(normals, offsets, yb, cand[i, 0], cand[i, 1])
            turn = _sign(rate_a) != _sign(rate_b) or abs(rate_a) + abs(rate_b) <= point_acc * dt
            if not (edge_a != edge_b or turn):
                continue
        out[i] = True
    for k in range(m):
        da = ya[3] * dirs[k, 0] + ya[4] * dirs[k, 1]
        db = yb[3] * dirs[k, 0] + yb[4] * dirs[k, 1]
        turn = _sign(da) != _sign(db) or abs(da) + abs(db) <= grad[k] * acc * dt
        out[nc + k] = turn and abs(ga[nc + k]) + abs(gb[nc + k]) <= grad[k] * speed * dt
    for i in range(nc + m):
        noise = _noise(nc, m, noise_length, noise_force, i)
        out[i] = out[i] and abs(ga[i]) > noise and abs(gb[i]) > noise
        any_hidden = any_hidden or out[i]
    return any_hidden


@leaf
def dense_at(F, y_old, t_old, h, t, out):
    """DOP853's dense output (scipy's ``Dop853DenseOutput``) of the step from ``t_old`` of length ``h`` at ``t``."""
    x = (t - t_old) / h
    for j in range(6):
        out[j] = 0.0
    nF = F.shape[0]
    for i in range(nF):
        w = x if i % 2 == 0 else 1 - x
        for j in range(6):
            out[j] = (out[j] + F[nF - 1 - i, j]) * w
    for j in range(6):
        out[j] += y_old[j]


@leaf
def _changed(g, g0, out):
    """Which values' signs differ from the baseline ``g0``, into ``out``; whether any."""
    anyc = False
    for i in range(g.shape[0]):
        out[i] = (g[i] > 0) != g0[i]
        anyc = anyc or out[i]
    return anyc


@leaf
def _unchanged(hidden, changed, out):
    """``hidden`` where the value did not already change sign (a change is found, not hidden), into ``out`` (may
    be ``hidden`` itself); whether any."""
    anyh = False
    for i in range(out.shape[0]):
        out[i] = hidden[i] and not changed[i]
        anyh = anyh or out[i]
    return anyh


NOT_FOUND, FOUND, SEARCH_FULL = 0, 1, 2
"""What :func:`_first_change` and :func:`_search` report: no change in the interval, a bracket (in the scratch), or
the scratch's bisection stores too small (grow them: :func:`_grown_search`, and search again)."""
_SEARCH_CAP = 64
"""Intervals the bisection of one sample interval may hold before its stores are grown."""
_EPS = float(np.finfo(np.float64).eps)


class SearchScratch(NamedTuple):
    """The arrays a piece (:func:`_piece`), its steps' search for their first event (:func:`_first_change`,
    :func:`_search`) and its location (:func:`_locate`) work in, made once a loop (:func:`search_scratch`) rather
    than a dozen small ones every step, so that all of them are leaves (:data:`leaf`). Event-value arrays hold up to
    ``n`` values; a piece's ``n`` values (:func:`n_values`) are the first ``n`` of each.

    ``ts`` (S,), ``Y`` (S, 6), ``G`` (S, n): the step's samples (S = ``SUBSAMPLES`` + 1: times s, states, event values);
    ``changed``, ``hidden`` (n,): at a sample; ``s_changed``, ``s_hidden`` (n,), ``T`` (c,), ``SY`` (c, 6), ``SG``
    (c, n), ``stack`` (c, 2): the bisection's; ``out_changed``, ``g_a``, ``g_b`` (n,): the bracket found (which values
    changed, the values at its ends); ``idx`` (n,), ``sgn`` (n,), ``y`` (6,), ``g`` (n,), ``calls`` (1,): the
    location's (the changed values and their signs, a state, the values at the probe, evaluations). The piece's
    (:func:`_piece`): a DOP853 step's ``K``, ``F``, ``f``, ``y_new``, ``f_new``, ``work`` (:func:`_workspace`), the
    baseline's values ``g0v`` (n,) and signs ``g0`` (n,), the ``state`` (6,) it ends in, the ``restart`` (6,) and
    ``probe`` (6,) states of its event, and the cells ``under`` (n,) the footprint there."""

    ts: np.ndarray
    Y: np.ndarray
    G: np.ndarray
    changed: np.ndarray
    hidden: np.ndarray
    s_changed: np.ndarray
    s_hidden: np.ndarray
    T: np.ndarray
    SY: np.ndarray
    SG: np.ndarray
    stack: np.ndarray
    out_changed: np.ndarray
    g_a: np.ndarray
    g_b: np.ndarray
    idx: np.ndarray
    sgn: np.ndarray
    y: np.ndarray
    g: np.ndarray
    calls: np.ndarray
    K: np.ndarray
    F: np.ndarray
    f: np.ndarray
    y_new: np.ndarray
    f_new: np.ndarray
    work: np.ndarray
    g0v: np.ndarray
    g0: np.ndarray
    state: np.ndarray
    restart: np.ndarray
    probe: np.ndarray
    under: np.ndarray


@njit(cache=True)
def _scratch(n, cap):
    S = SUBSAMPLES + 1
    K, F, f, y_new, f_new, work = _workspace()
    return SearchScratch(np.empty(S), np.empty((S, 6)), np.empty((S, n)), np.empty(n, np.bool_),
                         np.empty(n, np.bool_), np.empty(n, np.bool_), np.empty(n, np.bool_), np.empty(cap),
                         np.empty((cap, 6)), np.empty((cap, n)), np.empty((cap, 2), np.int64), np.empty(n, np.bool_),
                         np.empty(n), np.empty(n), np.empty(n, np.int64), np.empty(n), np.empty(6), np.empty(n),
                         np.zeros(1, np.int64), K, F, f, y_new, f_new, work, np.empty(n), np.empty(n, np.bool_),
                         np.empty(6), np.empty(6), np.empty(6), np.empty(n, np.int64))


@njit(cache=True)
def search_scratch(n):
    """A :class:`SearchScratch` for up to ``n`` event values."""
    return _scratch(n, _SEARCH_CAP)


@njit(cache=True)
def _grown_search(sc):
    """A :class:`SearchScratch` as ``sc`` with bisection stores twice as long (its search said ``SEARCH_FULL``)."""
    return _scratch(sc.G.shape[1], 2 * sc.T.shape[0])


@leaf
def _linspace(start, stop, out):
    """``np.linspace(start, stop, len(out))`` into ``out``, as numba computes it (the same floats)."""
    num = out.shape[0]
    step = (stop - start) / (num - 1)
    for i in range(num):
        out[i] = start + (i * step)
    out[num - 1] = stop


@leaf
def _copy(a, out):
    """``out[:] = a`` element by element (a whole-array assignment may copy through a temporary: not in a leaf)."""
    for i in range(a.shape[0]):
        out[i] = a[i]


@leaf
def _search(seg, F, y_old, t_old, h, g0, acc, spin_acc, t0, t1, y0, y1, g0v, g1v, hidden0, sc):
    """The earliest bracket in [t0, t1] (states ``y0``, ``y1``, event values ``g0v``, ``g1v``) across which the event
    predicate leaves ``g0``, bisecting while a crossing could hide (``hidden0``: the whole interval's predicate):
    (found, t_a, t_b), the bracket's changed values and its ends' values into ``sc`` (``out_changed``, ``g_a``,
    ``g_b``). Depth first, earliest half first. ``SEARCH_FULL`` when the scratch's stores are too small."""
    n = g0.shape[0]
    T, Y, G, stack = sc.T, sc.SY, sc.SG, sc.stack
    T[0], T[1] = t0, t1
    _copy(y0, Y[0])
    _copy(y1, Y[1])
    _copy(g0v, G[0, :n])
    _copy(g1v, G[1, :n])
    used = 2
    stack[0, 0], stack[0, 1] = 0, 1
    depth = 1
    changed, hidden = sc.s_changed[:n], sc.s_hidden[:n]
    first = True
    while depth > 0:
        depth -= 1
        a, b = stack[depth, 0], stack[depth, 1]
        anyc = _changed(G[b, :n], g0, changed)
        if first:
            anyh = _unchanged(hidden0, changed, hidden)
            first = False
        else:
            may_hide(seg, Y[a], Y[b], G[a, :n], G[b, :n], T[b] - T[a], acc, spin_acc, hidden)
            anyh = _unchanged(hidden, changed, hidden)
        if not anyh or T[b] - T[a] <= MIN_BRACKET:
            if anyc:
                _copy(changed, sc.out_changed[:n])
                _copy(G[a, :n], sc.g_a[:n])
                _copy(G[b, :n], sc.g_b[:n])
                return FOUND, T[a], T[b]
            continue
        if used == T.shape[0] or depth + 2 > stack.shape[0]:
            return SEARCH_FULL, t0, t1
        mid = used
        used += 1
        T[mid] = 0.5 * (T[a] + T[b])
        dense_at(F, y_old, t_old, h, T[mid], Y[mid])
        values(seg, Y[mid], G[mid, :n])
        stack[depth, 0], stack[depth, 1] = mid, b  # the later half waits
        stack[depth + 1, 0], stack[depth + 1, 1] = a, mid
        depth += 2
    return NOT_FOUND, t0, t1


@leaf
def _phi(t, ctx):
    """min_k s_k g_k(t) over the changed event values ``idx``: its first zero is the earliest crossing. ``ctx`` is
    (segment, dense output F, y_old, t_old, h, idx, s_k, a work array for the state and a count of evaluations).
    Only the changed values are computed (Brent's method evaluates this some ten times an event)."""
    seg, F, y_old, t_old, h, idx, sgn, y, calls = ctx
    calls[0] += 1
    dense_at(F, y_old, t_old, h, t, y)
    out = np.inf
    for k in range(idx.shape[0]):
        out = min(out, sgn[k] * value(seg, y, idx[k]))
    return out


@leaf
def _brent(ctx, xa, xb, fa, fb, xtol, rtol, maxiter):
    """A root of :func:`_phi` (``ctx``) between ``xa`` and ``xb``, whose values there, ``fa`` and ``fb``, have
    opposite signs (or one is zero), to within ``xtol + rtol |x|``: Brent's method as ``scipy.optimize.brentq`` runs
    it (C. Harris's variant, with the same steps and the same arithmetic, so the same root), without evaluating the
    two ends again: the event engine knows them. Returns (root, outcome): ``REACHED``, or ``NOT_FINITE`` (phi was not
    finite at the returned point) or ``NO_CONVERGENCE``."""
    xpre, xcur, fpre, fcur = xa, xb, fa, fb
    if fpre == 0:
        return xpre, REACHED
    if fcur == 0:
        return xcur, REACHED
    xblk = fblk = spre = scur = 0.0
    for _ in range(maxiter):
        if fpre != 0 and fcur != 0 and math.copysign(1.0, fpre) != math.copysign(1.0, fcur):
            xblk, fblk = xpre, fpre  # the root lies between xcur and xblk
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2
        sbis = (xblk - xcur) / 2
        if fcur == 0 or abs(sbis) < delta:
            return xcur, REACHED
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:  # secant
                stry = -fcur * (xcur - xpre) / (fcur - fpre)
            else:  # inverse quadratic extrapolation
                dpre = (fpre - fcur) / (xpre - xcur)
                dblk = (fblk - fcur) / (xblk - xcur)
                stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
            if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - delta):
                spre, scur = scur, stry
            else:
                spre = scur = sbis
        else:
            spre = scur = sbis
        xpre, fpre = xcur, fcur
        xcur += scur if abs(scur) > delta else (delta if sbis > 0 else -delta)
        fcur = _phi(xcur, ctx)
        if not math.isfinite(fcur):
            return xcur, NOT_FINITE
    return xcur, NO_CONVERGENCE


@leaf
def _locate(seg, F, y_old, t_old, h, g0, t_lo, t_hi, changed, g_lo, g_hi, sc):
    """The earliest event in (t_lo, t_hi], whose ends have event values ``g_lo``, ``g_hi``: (outcome, restart,
    probe, whether the probe's values are clear of rounding noise); the probe's values into ``sc.g`` (its first
    ``len(g0)``), the scratch's location arrays used (:class:`SearchScratch`).

    The earliest crossing is the first zero of ``min_k s_k g_k(t)`` over the changed event functions, with ``s_k``
    the sign that makes each positive before its crossing; it is bracketed by the caller and found by Brent's method.
    ``restart`` is just past that root: the integration continues from there with the new piece. ``probe`` is a
    little later, where every event value is clear of rounding noise: the new piece and its event baseline are read
    there, so that cells crossing together by symmetry all cross and no tie at the root decides the piece."""
    n = g0.shape[0]
    nc, m, noise_length, noise_force = seg.candidates.shape[0], seg.basis.shape[0], seg.noise_length, seg.noise_force
    count = 0
    for i in range(n):  # the changed values' indices, in order (np.flatnonzero)
        if changed[i]:
            sc.idx[count] = i
            count += 1
    idx, sgn = sc.idx[:count], sc.sgn[:count]
    phi_lo = phi_hi = np.inf
    for k in range(idx.shape[0]):
        sgn[k] = 1.0 if g0[idx[k]] else -1.0
        phi_lo = min(phi_lo, sgn[k] * g_lo[idx[k]])
        phi_hi = min(phi_hi, sgn[k] * g_hi[idx[k]])
    y, g = sc.y, sc.g[:n]
    eps = _EPS
    xtol = max(4 * eps * abs(t_hi), 1e-13)
    outcome = REACHED
    if phi_lo <= 0.0:
        t_ev = t_lo
    elif phi_hi > 0.0:  # the change was a sign flip through an exact zero at t_hi
        t_ev = t_hi
    else:
        sc.calls[0] = 0
        ctx = (seg, F, y_old, t_old, h, idx, sgn, y, sc.calls)
        t_ev, outcome = _brent(ctx, t_lo, t_hi, phi_lo, phi_hi, xtol, 4 * eps, 100)
        if outcome != REACHED:
            return outcome, t_ev, t_ev, False
    step = PROBE_FIRST
    t_star = min(t_hi, t_ev + xtol)
    first = -1.0
    while True:
        dense_at(F, y_old, t_old, h, t_star, y)
        values(seg, y, g)
        differs = False
        clear = True
        for i in range(n):
            differs = differs or (g[i] > 0) != g0[i]
            clear = clear and abs(g[i]) > _noise(nc, m, noise_length, noise_force, i)
        if differs:
            if first < 0:
                first = t_star
            if clear:
                return REACHED, min(t_ev + xtol, t_star), t_star, True
        if t_star >= t_hi or t_star - t_ev > PROBE_MAX:
            probe = t_hi if first < 0 else first
            return REACHED, min(t_ev + xtol, probe), probe, False
        t_star = min(t_hi, t_ev + step)
        step *= 4


@leaf
def _first_change(seg, F, y_old, t_old, h, g0, t_lo, t_hi, f_lo, f_hi, sc):
    """The earliest bracket (t_a, t_b) in (t_lo, t_hi] across which the event predicate leaves ``g0``: (found, t_a,
    t_b), the bracket's changed values and its ends' values into ``sc`` (``out_changed``, ``g_a``, ``g_b``);
    ``SEARCH_FULL``: grow the scratch's stores and search again.

    The step is sampled at ``SUBSAMPLES`` points. Between two samples an event function can cross zero and come
    back (a cell grazing the footprint's edge) only if it could reach zero in that time (:func:`may_hide`); such
    intervals are bisected, earliest first, until the crossing is found or ruled out (down to ``MIN_BRACKET``
    seconds). A bracket is returned only once no other component could hide an earlier crossing inside it.
    ``f_lo``, ``f_hi`` are the state derivatives at the step's ends, from which the acceleration bounds are taken
    with a safety factor. A sample's values are computed when its interval is examined: most steps of a piece end
    in its event, a third of the way along on average (an oscillating Coulomb parcel), and the samples past it
    were most of the search's work."""
    n = g0.shape[0]
    ts, Y, G = sc.ts, sc.Y, sc.G
    _linspace(t_lo, t_hi, ts)
    dense_at(F, y_old, t_old, h, ts[0], Y[0])
    values(seg, Y[0], G[0, :n])
    acc = RATE_SAFETY * max(math.hypot(f_lo[3], f_lo[4]), math.hypot(f_hi[3], f_hi[4]))
    spin_acc = RATE_SAFETY * max(abs(f_lo[5]), abs(f_hi[5]))
    changed, hidden = sc.changed[:n], sc.hidden[:n]
    for j in range(SUBSAMPLES):
        dense_at(F, y_old, t_old, h, ts[j + 1], Y[j + 1])
        values(seg, Y[j + 1], G[j + 1, :n])
        anyc = _changed(G[j + 1, :n], g0, changed)
        may_hide(seg, Y[j], Y[j + 1], G[j, :n], G[j + 1, :n], ts[j + 1] - ts[j], acc, spin_acc, hidden)
        anyh = _unchanged(hidden, changed, hidden)
        if anyc or anyh:
            found, t_a, t_b = _search(seg, F, y_old, t_old, h, g0, acc, spin_acc, ts[j], ts[j + 1], Y[j], Y[j + 1],
                                      G[j, :n], G[j + 1, :n], hidden, sc)
            if found != NOT_FOUND:
                return found, t_a, t_b
    return NOT_FOUND, t_lo, t_hi


@leaf
def _event_in_step(seg, F, y_old, t_old, h, g0, t_lo, t_hi, f_lo, f_hi, sc):
    """:func:`_first_change` over (t_lo, t_hi] and, where it finds a bracket, :func:`_locate` of the event in it:
    (found, outcome, restart time, probe time, whether the probe's values are clear of rounding noise), the probe's
    values in ``sc.g``; not found: the restart time ``t_hi``. ``SEARCH_FULL``: grow the scratch (:func:`_grown_search`)
    and call again."""
    found, t_a, t_b = _first_change(seg, F, y_old, t_old, h, g0, t_lo, t_hi, f_lo, f_hi, sc)
    if found != FOUND:
        return found, REACHED, t_hi, t_hi, False
    n = g0.shape[0]
    outcome, t_reach, t_probe, clear = _locate(seg, F, y_old, t_old, h, g0, t_a, t_b, sc.out_changed[:n],
                                               sc.g_a[:n], sc.g_b[:n], sc)
    return FOUND, outcome, t_reach, t_probe, clear


@leaf
def _rhs(row, y, out):
    out[0], out[1], out[2] = y[3], y[4], y[5]
    out[3], out[4], out[5] = accelerations_compiled(row, y[0], y[1], y[3], y[4], y[5])


@leaf
def _stage(row, y, h, K, a, s, work):
    """Stage ``s`` of a Runge-Kutta step from ``y`` of length ``h``: ``K[s] = rhs(y + h sum_i<s a_i K_i)``."""
    for j in range(6):
        dy = 0.0
        for i in range(s):
            dy += K[i, j] * a[i]
        work[j] = y[j] + dy * h
    _rhs(row, work, K[s])


@leaf
def _trial(row, y, f, h, rtol, atol, K, y_new, f_new, work):
    """A trial step of DOP853 of length ``h`` from ``y`` with derivative ``f`` (scipy's ``rk_step``): fills the
    stages ``K``, ``y_new`` and ``f_new``; returns the error norm (scipy's ``_estimate_error_norm``), below 1 for a
    step DOP853 accepts."""
    for j in range(6):  # (a row assigned whole may copy, with the runtime a leaf has not)
        K[0, j] = f[j]
    for s in range(1, _N_STAGES):
        _stage(row, y, h, K, _A[s], s, work)
    for j in range(6):
        acc = 0.0
        for i in range(_N_STAGES):
            acc += K[i, j] * _B[i]
        y_new[j] = y[j] + h * acc
    _rhs(row, y_new, f_new)
    for j in range(6):
        K[_N_STAGES, j] = f_new[j]
    err5 = err3 = 0.0
    for j in range(6):
        scale = atol + max(abs(y[j]), abs(y_new[j])) * rtol
        e5 = e3 = 0.0
        for i in range(_N_STAGES + 1):
            e5 += K[i, j] * _E5[i]
            e3 += K[i, j] * _E3[i]
        err5 += (e5 / scale) ** 2
        err3 += (e3 / scale) ** 2
    if err5 == 0 and err3 == 0:
        return 0.0
    return abs(h) * err5 / math.sqrt((err5 + 0.01 * err3) * 6)


@leaf
def _dop853_step(row, t, y, f, t_bound, h_abs, rtol, atol, max_step, K, y_new, f_new, work):
    """One accepted step of scipy's DOP853 (``RungeKutta._step_impl``) from (t, y) with derivative f: fills
    ``y_new``, ``f_new`` and the stages ``K``; returns (ok, t_new, h_abs for the next step, evaluations)."""
    min_step = 10 * abs(np.nextafter(t, np.inf) - t)
    if h_abs > max_step:
        h_abs = max_step
    elif h_abs < min_step:
        h_abs = min_step
    rejected = False
    nfev = 0
    while True:
        if h_abs < min_step:
            return False, t, h_abs, nfev
        t_new = t + h_abs
        if t_new - t_bound > 0:
            t_new = t_bound
        h = t_new - t
        h_abs = abs(h)
        norm = _trial(row, y, f, h, rtol, atol, K, y_new, f_new, work)
        nfev += _N_STAGES
        if norm < 1:
            factor = _MAX_FACTOR if norm == 0 else min(_MAX_FACTOR, _SAFETY * norm ** _ERROR_EXPONENT)
            if rejected:
                factor = min(1.0, factor)
            return True, t_new, h_abs * factor, nfev
        factor = _SAFETY * norm ** _ERROR_EXPONENT  # a non-finite norm (overflowing trial) shrinks by MIN_FACTOR
        h_abs *= factor if factor > _MIN_FACTOR else _MIN_FACTOR
        rejected = True


@leaf
def _dense(row, t_old, y_old, f_old, y_new, f_new, h, K, F, work):
    """The step's dense-output coefficients F (7, 6) (scipy's ``DOP853._dense_output_impl``); evaluations made."""
    for e in range(_A_EXTRA.shape[0]):
        _stage(row, y_old, h, K, _A_EXTRA[e], _N_STAGES + 1 + e, work)
    for j in range(6):
        delta = y_new[j] - y_old[j]
        F[0, j] = delta
        F[1, j] = h * f_old[j] - delta
        F[2, j] = 2 * delta - h * (f_new[j] + f_old[j])
        for r in range(_D.shape[0]):
            acc = 0.0
            for i in range(_N_EXTENDED):
                acc += _D[r, i] * K[i, j]
            F[3 + r, j] = h * acc
    return _A_EXTRA.shape[0]


@njit(cache=True)
def _workspace():
    """Scratch arrays of a DOP853 step: the stages K, the dense-output coefficients F, and four states (the
    derivative at the start, the new state and its derivative, a stage's argument)."""
    return (np.empty((_N_EXTENDED, 6)), np.empty((_D.shape[0] + 3, 6)), np.empty(6), np.empty(6), np.empty(6),
            np.empty(6))


@njit(cache=True)
def quiet_steps(rows, Y, t, t_bound, rtol, atol, sample_times, out):
    """For each parcel k, with constants ``rows[k]`` (:func:`~virtual_vehicle.engine.dynamics.constants_row`,
    (n, :data:`~virtual_vehicle.physics.laws.affine.ROW_LENGTH`)) at state ``Y[k]`` (n, 6), the first step
    :func:`run_piece` takes from ``t`` to ``t_bound`` (s) on a new piece, when that step reaches ``t_bound`` and
    DOP853 accepts it whole: then ``out[k, j]`` is its dense output at ``sample_times[j]`` (in [t, t_bound]), as
    :func:`run_piece` samples it. The same code as :func:`run_piece`'s, so a window with no event ends where the
    event engine ends it, to the last bit. Returns which parcels' steps were accepted and the right-hand-side
    evaluations each took."""
    n = Y.shape[0]
    accepted = np.zeros(n, np.bool_)
    K, F, f, y_new, f_new, work = _workspace()
    min_step = 10 * abs(np.nextafter(t, np.inf) - t)
    h_abs = max(t_bound - t, min_step)  # _dop853_step's first trial from run_piece's first step
    t_new = t + h_abs
    if t_new - t_bound > 0:
        t_new = t_bound
    h = t_new - t
    if t_new != t_bound:  # rounding left a sliver: run_piece would take a second step
        return accepted, 0
    for k in range(n):
        y = Y[k]
        _rhs(rows[k], y, f)
        if _trial(rows[k], y, f, h, rtol, atol, K, y_new, f_new, work) < 1:
            accepted[k] = True
            _dense(rows[k], t, y, f, y_new, f_new, h, K, F, work)
            for j in range(sample_times.shape[0]):
                dense_at(F, y, t, h, sample_times[j], out[k, j])
    return accepted, 1 + _N_STAGES + _A_EXTRA.shape[0]


@njit(cache=True)
def run_piece(row, fields, y_base, t, y, t_bound, h_abs, first_step, rtol, atol, max_step, max_steps,
              sample_times, next_sample, samples, sc):
    """Integrate one piece from (t, y) towards ``t_bound`` until its first event, ``max_steps`` steps, or the end.

    ``row`` is the piece's constants row, ``fields`` its :class:`Segment`'s (:func:`make_segment`), ``y_base`` the
    state at which the event values' signs are the baseline (the piece's start, or the probe just past the event that
    began it). The first step tried is ``first_step`` when positive (a new piece), else ``h_abs`` (the same piece
    resumed after a pause). Output samples ``sample_times[next_sample:]`` reached are written into ``samples``.
    ``sc`` is the loop's scratch (:func:`search_scratch`; a larger one is made here if it holds too few values).
    Times in s, states in SI units. (:func:`_piece`, the leaf that does it, for a caller from Python: the event loop
    calls the leaf.)

    Returns (outcome, t, y, h_abs, last step, evaluations, next_sample, probe time, probe state, the cells under the
    footprint at the probe (ids, as :meth:`~virtual_vehicle.engine.dynamics._Segment.support` finds them from the
    probe's event values), whether those tell: the values clear of rounding noise and the probe within the candidates'
    reach). On ``EVENT`` (t, y) is the restart point just past it.
    """
    seg = Segment(*fields)
    n = n_values(seg)
    if sc.G.shape[1] < n:
        sc = search_scratch(n)
    nfev = 0
    while True:
        (outcome, t, h_abs, last, evals, next_sample, t_probe, n_under,
         told) = _piece(row, seg, y_base, t, y, t_bound, h_abs, first_step, rtol, atol, max_step, max_steps,
                        sample_times, next_sample, samples, sc)
        nfev += evals
        if outcome != SEARCH_OUT:
            return (outcome, t, sc.state.copy(), h_abs, last, nfev, next_sample, t_probe, sc.probe.copy(),
                    sc.under[:n_under].copy(), told)
        y, first_step, sc = sc.state.copy(), 0.0, _grown_search(sc)


SEARCH_OUT = 6
"""An outcome of :func:`_piece` besides run_piece's: a step's search outgrew the scratch's stores; grow them
(:func:`_grown_search`) and call again from the state it stopped in (``state``) with ``first_step`` 0: the same
step is taken again (one more evaluation counted), the same event found."""


@leaf
def _piece(row, seg, y_base, t, y0, t_bound, h_abs, first_step, rtol, atol, max_step, max_steps, sample_times,
           next_sample, samples, sc):
    """:func:`run_piece` on :class:`Segment` ``seg`` from (t, ``y0``), working in scratch ``sc`` (room for the
    piece's event values): a leaf, so a piece begun in the event loop counts none of its arrays and makes none.
    Returns (outcome, t, h_abs, last step, evaluations, next_sample, probe time, cells under the footprint at the
    probe (how many: their ids in ``sc.under``), whether those tell); the state it ends in (the restart point on
    ``EVENT``) in ``sc.state``, the probe state in ``sc.probe``. ``SEARCH_OUT``: see there."""
    n = n_values(seg)
    g0v, g0 = sc.g0v[:n], sc.g0[:n]
    values(seg, y_base, g0v)
    for i in range(n):
        g0[i] = g0v[i] > 0
    K, F, f, y_new, f_new, work, y = sc.K, sc.F, sc.f, sc.y_new, sc.f_new, sc.work, sc.state
    _copy(y0, y)
    _rhs(row, y, f)
    nfev = 1
    if first_step > 0:
        h_abs = first_step
    last = 0.0
    steps = 0
    while t < t_bound:
        if steps == max_steps:
            return PAUSED, t, h_abs, last, nfev, next_sample, t, 0, False
        ok, t_new, h_next, evals = _dop853_step(row, t, y, f, t_bound, h_abs, rtol, atol, max_step, K, y_new,
                                                f_new, work)
        nfev += evals
        if not ok:
            return FAILED, t, h_abs, last, nfev, next_sample, t, 0, False
        steps += 1
        h = t_new - t
        last = h
        nfev += _dense(row, t, y, f, y_new, f_new, h, K, F, work)
        found, outcome, t_reach, t_probe, clear = _event_in_step(seg, F, y, t, h, g0, t, t_new, f, f_new, sc)
        if found == SEARCH_FULL:  # (the step not taken: the caller grows the stores and calls again)
            return SEARCH_OUT, t, h_abs, last, nfev, next_sample, t, 0, False
        if found and outcome != REACHED:
            return outcome, t_reach, h_next, last, nfev, next_sample, t, 0, False
        while next_sample < sample_times.shape[0] and sample_times[next_sample] <= t_reach:
            dense_at(F, y, t, h, sample_times[next_sample], samples[next_sample])
            next_sample += 1
        if found:
            dense_at(F, y, t, h, t_reach, sc.restart)
            dense_at(F, y, t, h, t_probe, sc.probe)
            _copy(sc.restart, y)
            g = sc.g[:n]
            told = clear and g[n - 1] > 0
            count = _positive_into(seg.ids, g, sc.under) if told else 0
            return EVENT, t_reach, h_next, last, nfev, next_sample, t_probe, count, told
        t = t_new
        _copy(y_new, y)
        _copy(f_new, f)
        h_abs = h_next
    return REACHED, t, h_abs, last, nfev, next_sample, t, 0, False


@leaf
def _positive_into(ids, g, out):
    """The ``ids`` whose value in ``g`` (the candidates' margins first) is positive, in order, into ``out``; how
    many."""
    count = 0
    for i in range(ids.shape[0]):
        if g[i] > 0:
            out[count] = ids[i]
            count += 1
    return count


@njit(cache=True)
def _positive(ids, g):
    """:func:`_positive_into` in an array of its own."""
    out = np.empty(ids.shape[0], np.int64)
    return out[:_positive_into(ids, g, out)].copy()


@njit(cache=True)
def edges_clear(positions, near, normals, offsets, y, window, reach, accel, radius, lever, noise):
    """Whether no cell ``near`` (ids into ``positions``, (n, 2) m) of a convex parcel at state ``y`` can cross its
    outline (body-frame outward unit ``normals`` (k, 2), ``offsets`` (k,) m) within ``window`` s, edge by edge: the
    bound of :meth:`virtual_vehicle.engine.batch.QuietStepper._edges_clear`, which documents it, for one parcel
    (``reach`` and ``accel`` in m, ``radius`` m, ``lever`` = 1 + m R^2 / I, ``noise`` m)."""
    c, s = math.cos(y[2]), math.sin(y[2])
    drift = accel / lever
    turn = abs(y[5]) * window + (accel - drift) / radius
    shift = min(reach, math.hypot(y[3], y[4]) * window + drift)
    base = drift + noise + turn * shift
    for i in range(near.shape[0]):
        dx = positions[near[i], 0] - y[0]
        dy = positions[near[i], 1] - y[1]
        bound = base + turn * math.hypot(dx, dy)
        low, high = np.inf, np.inf
        for e in range(offsets.shape[0]):
            nx = c * normals[e, 0] - s * normals[e, 1]  # world normals
            ny = s * normals[e, 0] + c * normals[e, 1]
            h = offsets[e] - (nx * dx + ny * dy)
            toward = (nx * y[3] + ny * y[4]) * window
            low = min(low, h + min(toward, 0.0) - bound)
            high = min(high, h + max(toward, 0.0) + bound)
        if not (low > 0 or high < 0):  # neither surely inside nor surely beyond an edge
            return False
    return True


@njit(cache=True)
def edges_clear_many(positions, near, near_count, normals, offsets, edge_count, Y, window, reach, accel, radius,
                     lever, noise):
    """:func:`edges_clear` for many parcels in one call (each call took ~4 us, most of it its eleven arguments):
    parcel k's cells are ``near[k, :near_count[k]]``, its edges ``normals[k, :edge_count[k]]`` and ``offsets[k,
    :edge_count[k]]`` (rows padded beyond), its state ``Y[k]``; ``reach``, ``accel``, ``radius``, ``lever`` and
    ``noise`` are arrays by parcel. Returns a bool array by parcel."""
    out = np.empty(Y.shape[0], np.bool_)
    for k in range(Y.shape[0]):
        e = edge_count[k]
        out[k] = edges_clear(positions, near[k, :near_count[k]], normals[k, :e], offsets[k, :e], Y[k], window,
                             reach[k], accel[k], radius[k], lever[k], noise[k])
    return out


# -- A law with modes (stick-slip, :mod:`virtual_vehicle.physics.stick_modes`): one mode of one piece ---------------
#
# A mode is passed as the plain tuple :func:`mode_fields` makes: (points (m, 2) m, directions (m, 2), surface speeds
# (m,) m/s at time t0, their rates (m,) m/s^2, t0 s, the normal-force map force_lin (m, 2) N/m, force_const (m,) N and
# origin (2,) m, mu_static (m,), mu_kinetic (m,), state (m,) int64 (0 sticks, +-1 slips with that sign, 2 free),
# independent sticking rows (r,) int64 (r <= 3), all sticking wheels (k,) int64, and the facet choice of their
# zonotope: rank, anchor (2,) int64, index (f, 2) int64, then the inverse masses (3,) 1/kg, 1/kg, 1/(kg m^2)).
# The state integrated is 8 long: the parcel's six, then the wheels' work and the friction dissipation so far (J).

MODE_EVENT = 6
"""Outcome of :func:`run_mode`: a mode event (a slipping wheel's slip reached zero, or the sticking wheels' required
wrench a facet of their zonotope) ended the mode; the Python side decides the next mode there."""
_C, _C_EXTRA = (np.ascontiguousarray(a, dtype=np.float64) for a in (DOP853.C, DOP853.C_EXTRA))
_MODE_STATE = 8


def mode_fields(wheels, state, rows, stick, spec, minv) -> tuple:
    """The tuple :func:`run_mode` takes for ``wheels`` (a :class:`~virtual_vehicle.physics.stick_modes.Wheels`) in
    mode ``state`` ((m,) ints), with independent sticking rows ``rows``, sticking wheels ``stick`` and the facet
    choice ``spec`` (rank, anchor or None, (f, 2) or (f,) indices into ``stick``) of their zonotope, for inverse
    masses ``minv`` (3,)."""
    def arr(a, dtype=np.float64):
        return np.ascontiguousarray(a, dtype=dtype)

    rank, anchor, index = spec
    index = arr(index, np.int64)
    index = index.reshape(len(index), -1) if index.size else np.zeros((0, 2), np.int64)
    if index.shape[1] == 1:
        index = np.column_stack([index, index])
    return (arr(wheels.points).reshape(-1, 2), arr(wheels.directions).reshape(-1, 2), arr(wheels.speeds),
            arr(wheels.accels), float(wheels.t0), arr(wheels.force_lin).reshape(-1, 2), arr(wheels.force_const),
            arr(wheels.origin), arr(wheels.mu_static), arr(wheels.mu_kinetic), arr(state, np.int64),
            arr(rows, np.int64), arr(stick, np.int64), int(rank),
            arr((0, 0) if anchor is None else anchor, np.int64), index.reshape(-1, 2), arr(minv))


@njit(cache=True)
def _mode_dynamics(md, t, z, F_S):
    """Accelerations of mode ``md`` at time ``t`` (s), state ``z``: returns (ax, ay, alpha, wheel power, friction
    power lost) in m/s^2, rad/s^2, W, W and fills ``F_S`` (3,) with the sticking wheels' net wrench (N, N, N m).

    Slipping wheels push with ``-sign mu_k N`` along their directions (eq. 22 per wheel, eq. 19 for N); the sticking
    rows ``J_R nu_dot + c = w_dot`` (``c = -omega (v x u)``) fix their forces, solved in closed form (at most three
    independent rows); the other sticking wheels' rows follow from these (their dependence does not change as the
    centre moves, as ``J(X) = J(0) T(X)`` with T invertible)."""
    (P, U, w0, wa, t0, FL, FC, origin, mus, muk, state, R, S, rank, anchor, index, minv) = md
    x0, x1, vx, vy, om = z[0] - origin[0], z[1] - origin[1], z[3], z[4], z[5]
    kx = ky = kt = 0.0
    work = lost = 0.0
    for j in range(state.shape[0]):
        sj = state[j]
        if sj == 1 or sj == -1:
            N = FL[j, 0] * x0 + FL[j, 1] * x1 + FC[j]
            lam = -sj * muk[j] * N  # eq. 22 per wheel: mu N along the direction it outruns the parcel
            ux, uy = U[j, 0], U[j, 1]
            arm = (P[j, 0] - z[0]) * uy - (P[j, 1] - z[1]) * ux
            kx += lam * ux
            ky += lam * uy
            kt += lam * arm
            w = w0[j] + wa[j] * (t - t0)
            work += lam * w
            lost -= lam * (ux * vx + uy * vy + arm * om - w)
    F_S[0] = F_S[1] = F_S[2] = 0.0
    r = R.shape[0]
    if r > 0:
        J = np.empty((3, 3))
        A = np.empty((3, 3))
        b = np.empty(3)
        for a in range(r):
            j = R[a]
            ux, uy = U[j, 0], U[j, 1]
            J[a, 0], J[a, 1], J[a, 2] = ux, uy, (P[j, 0] - z[0]) * uy - (P[j, 1] - z[1]) * ux
            c = -om * (vx * uy - vy * ux)  # d/dt (r x u) omega, with dr/dt = -v
            b[a] = wa[j] - c - (J[a, 0] * minv[0] * kx + J[a, 1] * minv[1] * ky + J[a, 2] * minv[2] * kt)
        for a in range(r):
            for q in range(r):
                A[a, q] = J[a, 0] * minv[0] * J[q, 0] + J[a, 1] * minv[1] * J[q, 1] + J[a, 2] * minv[2] * J[q, 2]
        lam = _solve_small(A, b, r)
        for a in range(r):
            F_S[0] += J[a, 0] * lam[a]
            F_S[1] += J[a, 1] * lam[a]
            F_S[2] += J[a, 2] * lam[a]
        work += F_S[0] * vx + F_S[1] * vy + F_S[2] * om  # sticking wheels: sum lam w = sum lam J nu (no slip)
    return minv[0] * (kx + F_S[0]), minv[1] * (ky + F_S[1]), minv[2] * (kt + F_S[2]), work, lost


@njit(cache=True)
def _solve_small(A, b, r):
    """``A[:r, :r] x = b[:r]`` by Gaussian elimination with partial pivoting (r <= 3, A symmetric positive
    definite: the sticking rows are independent)."""
    M = A.copy()
    x = b.copy()
    for c in range(r):
        p = c
        for i in range(c + 1, r):
            if abs(M[i, c]) > abs(M[p, c]):
                p = i
        if p != c:
            for k in range(r):
                M[c, k], M[p, k] = M[p, k], M[c, k]
            x[c], x[p] = x[p], x[c]
        for i in range(c + 1, r):
            f = M[i, c] / M[c, c]
            for k in range(c, r):
                M[i, k] -= f * M[c, k]
            x[i] -= f * x[c]
    out = np.zeros(r)
    for i in range(r - 1, -1, -1):
        acc = x[i]
        for k in range(i + 1, r):
            acc -= M[i, k] * out[k]
        out[i] = acc / M[i, i]
    return out


@njit(cache=True)
def _mode_rhs(md, t, z, out):
    """The 8-long state's rate in mode ``md``: velocities, accelerations, wheel power and friction loss (W)."""
    F_S = np.empty(3)
    ax, ay, al, work, lost = _mode_dynamics(md, t, z, F_S)
    out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7] = z[3], z[4], z[5], ax, ay, al, work, lost


def mode_event_count(md) -> int:
    """Number of mode event values of ``md``: one per slipping wheel, then one per facet of the sticking wheels'
    zonotope."""
    state, S, index = md[10], md[12], md[15]
    return int(np.count_nonzero(np.abs(state) == 1)) + (len(index) if len(S) else 0)


@njit(cache=True)
def mode_values(md, t, z, out):
    """Mode event values of ``md`` at time ``t`` (s), state ``z`` into ``out``; each falls through zero at its event.
    Per slipping wheel its slip speed times its sign (m/s); per facet of the sticking wheels' zonotope (generators
    ``mu_s N J``) its support along the facet's normal less the required wrench's (N or N m): the rule of
    :mod:`virtual_vehicle.physics.stick_modes`."""
    (P, U, w0, wa, t0, FL, FC, origin, mus, muk, state, R, S, rank, anchor, index, minv) = md
    x0, x1 = z[0] - origin[0], z[1] - origin[1]
    n = 0
    for j in range(state.shape[0]):
        sj = state[j]
        if sj == 1 or sj == -1:
            ux, uy = U[j, 0], U[j, 1]
            arm = (P[j, 0] - z[0]) * uy - (P[j, 1] - z[1]) * ux
            out[n] = sj * (ux * z[3] + uy * z[4] + arm * z[5] - w0[j] - wa[j] * (t - t0))
            n += 1
    k = S.shape[0]
    if k == 0:
        return
    F_S = np.empty(3)
    _mode_dynamics(md, t, z, F_S)
    G = np.empty((k, 3))
    for a in range(k):
        j = S[a]
        g = mus[j] * (FL[j, 0] * x0 + FL[j, 1] * x1 + FC[j])
        ux, uy = U[j, 0], U[j, 1]
        G[a, 0], G[a, 1], G[a, 2] = g * ux, g * uy, g * ((P[j, 0] - z[0]) * uy - (P[j, 1] - z[1]) * ux)
    nrm = np.empty(3)
    for f in range(index.shape[0]):
        p, q = index[f, 0], index[f, 1]
        if rank == 1:
            nrm[0], nrm[1], nrm[2] = G[p, 0], G[p, 1], G[p, 2]
        elif rank == 2:
            a0, a1 = anchor[0], anchor[1]
            px = G[a0, 1] * G[a1, 2] - G[a0, 2] * G[a1, 1]  # the span's normal
            py = G[a0, 2] * G[a1, 0] - G[a0, 0] * G[a1, 2]
            pz = G[a0, 0] * G[a1, 1] - G[a0, 1] * G[a1, 0]
            nrm[0] = py * G[p, 2] - pz * G[p, 1]
            nrm[1] = pz * G[p, 0] - px * G[p, 2]
            nrm[2] = px * G[p, 1] - py * G[p, 0]
        else:
            nrm[0] = G[p, 1] * G[q, 2] - G[p, 2] * G[q, 1]
            nrm[1] = G[p, 2] * G[q, 0] - G[p, 0] * G[q, 2]
            nrm[2] = G[p, 0] * G[q, 1] - G[p, 1] * G[q, 0]
        size = math.sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2])
        support = 0.0
        for a in range(k):
            support += abs(G[a, 0] * nrm[0] + G[a, 1] * nrm[1] + G[a, 2] * nrm[2])
        out[n + f] = (support - abs(F_S[0] * nrm[0] + F_S[1] * nrm[1] + F_S[2] * nrm[2])) / size


@njit(cache=True)
def _mode_stage(md, t, y, h, K, a, s, c, work):
    """Stage ``s`` of a Runge-Kutta step of mode ``md`` (node ``c``): ``K[s] = rhs(t + c h, y + h sum a_i K_i)``."""
    for j in range(_MODE_STATE):
        dy = 0.0
        for i in range(s):
            dy += K[i, j] * a[i]
        work[j] = y[j] + dy * h
    _mode_rhs(md, t + c * h, work, K[s])


@njit(cache=True)
def _mode_trial(md, t, y, f, h, rtol, atol, K, y_new, f_new, work):
    """:func:`_trial` for the 8-long state of a mode (the same DOP853 scheme and error norm)."""
    K[0] = f
    for s in range(1, _N_STAGES):
        _mode_stage(md, t, y, h, K, _A[s], s, _C[s], work)
    for j in range(_MODE_STATE):
        acc = 0.0
        for i in range(_N_STAGES):
            acc += K[i, j] * _B[i]
        y_new[j] = y[j] + h * acc
    _mode_rhs(md, t + h, y_new, f_new)
    K[_N_STAGES] = f_new
    err5 = err3 = 0.0
    for j in range(_MODE_STATE):
        scale = atol + max(abs(y[j]), abs(y_new[j])) * rtol
        e5 = e3 = 0.0
        for i in range(_N_STAGES + 1):
            e5 += K[i, j] * _E5[i]
            e3 += K[i, j] * _E3[i]
        err5 += (e5 / scale) ** 2
        err3 += (e3 / scale) ** 2
    if err5 == 0 and err3 == 0:
        return 0.0
    return abs(h) * err5 / math.sqrt((err5 + 0.01 * err3) * _MODE_STATE)


@njit(cache=True)
def _mode_step(md, t, y, f, t_bound, h_abs, rtol, atol, max_step, K, y_new, f_new, work):
    """:func:`_dop853_step` for a mode: (ok, t_new, h_abs for the next step, evaluations)."""
    min_step = 10 * abs(np.nextafter(t, np.inf) - t)
    if h_abs > max_step:
        h_abs = max_step
    elif h_abs < min_step:
        h_abs = min_step
    rejected = False
    nfev = 0
    while True:
        if h_abs < min_step:
            return False, t, h_abs, nfev
        t_new = t + h_abs
        if t_new - t_bound > 0:
            t_new = t_bound
        h = t_new - t
        h_abs = abs(h)
        norm = _mode_trial(md, t, y, f, h, rtol, atol, K, y_new, f_new, work)
        nfev += _N_STAGES
        if norm < 1:
            factor = _MAX_FACTOR if norm == 0 else min(_MAX_FACTOR, _SAFETY * norm ** _ERROR_EXPONENT)
            if rejected:
                factor = min(1.0, factor)
            return True, t_new, h_abs * factor, nfev
        factor = _SAFETY * norm ** _ERROR_EXPONENT
        h_abs *= factor if factor > _MIN_FACTOR else _MIN_FACTOR
        rejected = True


@njit(cache=True)
def _mode_dense(md, t_old, y_old, f_old, y_new, f_new, h, K, F, work):
    """:func:`_dense` for a mode's 8-long state; evaluations made."""
    for e in range(_A_EXTRA.shape[0]):
        _mode_stage(md, t_old, y_old, h, K, _A_EXTRA[e], _N_STAGES + 1 + e, _C_EXTRA[e], work)
    for j in range(_MODE_STATE):
        delta = y_new[j] - y_old[j]
        F[0, j] = delta
        F[1, j] = h * f_old[j] - delta
        F[2, j] = 2 * delta - h * (f_new[j] + f_old[j])
        for r in range(_D.shape[0]):
            acc = 0.0
            for i in range(_N_EXTENDED):
                acc += _D[r, i] * K[i, j]
            F[3 + r, j] = h * acc
    return _A_EXTRA.shape[0]


@njit(cache=True)
def _dense_all(F, y_old, t_old, h, t, out):
    """:func:`dense_at` for every column of ``F`` (the 8-long state of a mode)."""
    x = (t - t_old) / h
    for j in range(out.shape[0]):
        out[j] = 0.0
    nF = F.shape[0]
    for i in range(nF):
        w = x if i % 2 == 0 else 1 - x
        for j in range(out.shape[0]):
            out[j] = (out[j] + F[nF - 1 - i, j]) * w
    for j in range(out.shape[0]):
        out[j] += y_old[j]


@njit(cache=True)
def _mode_crossing(md, F, z_old, t_old, h, t_lo, t_hi, v_lo, n_ev):
    """The earliest mode event in (t_lo, t_hi] of the step (dense output ``F`` from ``z_old`` at ``t_old``, length
    ``h``), whose values at ``t_lo`` are ``v_lo``: (found, time just past its root, which value). The step is sampled
    at ``SUBSAMPLES`` points for values falling from positive to <= 0; in the first sample interval that has any,
    the earliest root among them is bisected to rounding as the first zero of their minimum (one bisection for all
    of them, not one each: wheels that catch up with a parcel together, as all wheels of one direction under a
    uniform field do, made a bisection each, some 300 us a catch-up), and the value is the first of them at or
    below zero there. Each bisection step moves the bracket as the earliest value's own bisection would (it is the
    first to fall), so the root is the one a bisection of that value alone finds, to the bit. (A value that dips
    through zero and back between two samples is not seen: a slipping wheel would have to catch up with its wheel
    and fall behind again within an eighth of a step.)"""
    y = np.empty(_MODE_STATE)
    v = np.empty(n_ev)
    prev = v_lo.copy()
    falling = np.empty(n_ev, np.bool_)
    t_a = t_lo
    eps = np.finfo(np.float64).eps
    for s in range(1, SUBSAMPLES + 1):
        t_b = t_lo + (t_hi - t_lo) * s / SUBSAMPLES if s < SUBSAMPLES else t_hi
        _dense_all(F, z_old, t_old, h, t_b, y)
        mode_values(md, t_b, y, v)
        for k in range(n_ev):
            falling[k] = prev[k] > 0 and not v[k] > 0
        which = _first_down(falling, v)
        if which >= 0:
            lo, hi = t_a, t_b
            while hi - lo > max(4 * eps * abs(hi), 1e-15):
                mid = 0.5 * (lo + hi)
                if mid <= lo or mid >= hi:
                    break
                _dense_all(F, z_old, t_old, h, mid, y)
                mode_values(md, mid, y, v)
                k = _first_down(falling, v)
                if k >= 0:
                    hi, which = mid, k
                else:
                    lo = mid
            return True, hi, which
        prev[:] = v
        t_a = t_b
    return False, t_hi, -1


@njit(cache=True)
def _first_down(falling, v):
    """The first of the values marked ``falling`` that is at or below zero in ``v``; -1 for none."""
    for k in range(v.shape[0]):
        if falling[k] and not v[k] > 0:
            return k
    return -1


RIDE_DRIFT = 1e-3
"""A mode is a riding translation (:func:`_rides_translation`) while the acceleration it neglects moves the parcel's
points by less than this fraction of the rounding noise in lengths over the rest of the call."""


@njit(cache=True)
def _rides_translation(md, f, seg, span):
    """Whether mode ``md`` (rates ``f`` at its start) is a parcel riding its wheels in translation, or turning about
    its centre, for the next ``span`` s: no wheel slips, no sticking wheel accelerates, and the accelerations the
    mode gives (``f[3:6]``: those of rounding alone in such a mode) would move no point of the parcel by
    :data:`RIDE_DRIFT` of the rounding noise over ``span``. Then the sticking wheels must supply no wrench (eqs.
    3-5 with no acceleration; ``m omega x v`` is zero or rounding), which lies inside their zonotope whatever the
    normal forces, so only a support event can end the mode, and the motion is the twist's, constant: the centre
    moves at ``v``, the heading at ``omega``."""
    state, wa = md[10], md[3]
    for j in range(state.shape[0]):
        if state[j] == 1 or state[j] == -1 or (state[j] == 0 and wa[j] != 0.0):
            return False
    drift = 0.5 * span * span * (math.hypot(f[3], f[4]) + abs(f[5]) * seg.reach)
    return drift <= RIDE_DRIFT * seg.noise_length


@njit(cache=True)
def _linear_motion(z, f, h, z_new, F):
    """A riding translation's step of ``h`` s from ``z`` (rates ``f``): the pose moves with the constant twist, the
    velocities stay, the energy account moves at its rates (zero but for rounding); ``F`` the dense output that
    :func:`dense_at` reads as that straight line (its highest-order row the change, the others zero)."""
    for j in range(_MODE_STATE):
        z_new[j] = z[j] + (h * z[3 + j] if j < 3 else (h * f[j] if j >= 6 else 0.0))
    for r in range(F.shape[0]):
        for j in range(_MODE_STATE):
            F[r, j] = 0.0
    for j in range(_MODE_STATE):
        F[0, j] = z_new[j] - z[j]  # dense_at's Horner form multiplies row 0 by x last (an odd number of rows)


@njit(cache=True)
def run_mode(md, n_ev, fields, y_base, t, z, t_bound, h_abs, first_step, rtol, atol, max_step, max_steps,
             sample_times, next_sample, samples):
    """:func:`run_piece` for one mode ``md`` (:func:`mode_fields`, with ``n_ev`` mode event values) of a law with
    modes on one piece (segment ``fields``): DOP853 on the 8-long state ``z`` (the parcel's six, the wheels' work
    and the friction dissipation, J) until its first support event (as :func:`run_piece` finds and locates them),
    its first mode event (:func:`_mode_crossing`), ``max_steps`` steps or ``t_bound``. A riding translation
    (:func:`_rides_translation`: the parcel carried by its sticking wheels without acceleration) takes no DOP853
    step: its motion is the straight line of its twist (:func:`_linear_motion`), searched for support events as a
    step is, with no mode event to look for.

    Returns (outcome, t, z, h_abs, last step, evaluations, next_sample, probe time, probe state, the cells under
    the footprint at the probe, whether those tell, the mode event's value index). On ``EVENT`` and ``MODE_EVENT``
    (t, z) is the restart point just past it."""
    seg = Segment(*fields)
    g0 = np.empty(n_values(seg))
    values(seg, y_base[:6].copy(), g0)
    g0 = g0 > 0
    n = g0.shape[0]
    sc = search_scratch(n)
    K = np.empty((_N_EXTENDED, _MODE_STATE))
    F = np.empty((_D.shape[0] + 3, _MODE_STATE))
    f, z_new, f_new, work = np.empty(8), np.empty(8), np.empty(8), np.empty(8)
    z = z.copy()
    _mode_rhs(md, t, z, f)
    riding = _rides_translation(md, f, seg, t_bound - t)
    v_lo = np.empty(n_ev)
    if not riding:
        mode_values(md, t, z, v_lo)
    nfev = 1
    if first_step > 0:
        h_abs = first_step
    last = 0.0
    y_probe = np.empty(6)
    none = np.empty(0, np.int64)
    steps = 0
    while t < t_bound:
        if steps == max_steps:
            return PAUSED, t, z, h_abs, last, nfev, next_sample, t, y_probe, none, False, -1
        if riding:  # the motion in closed form: no step to take, no mode event to meet (the step size kept)
            t_new = min(t_bound, t + max_step)
            h, h_next = t_new - t, h_abs
            _linear_motion(z, f, h, z_new, F)
            f_new[:] = f
            steps += 1
            moded, t_mode, which = False, t_new, -1
        else:
            ok, t_new, h_next, evals = _mode_step(md, t, z, f, t_bound, h_abs, rtol, atol, max_step, K, z_new,
                                                  f_new, work)
            nfev += evals
            if not ok:
                return FAILED, t, z, h_abs, last, nfev, next_sample, t, y_probe, none, False, -1
            steps += 1
            h = t_new - t
            last = h
            nfev += _mode_dense(md, t, z, f, z_new, f_new, h, K, F, work)
            moded, t_mode, which = (_mode_crossing(md, F, z, t, h, t, t_new, v_lo, n_ev) if n_ev
                                    else (False, t_new, -1))
        t_end = t_mode if moded else t_new
        found, outcome, t_reach, t_probe, clear = _event_in_step(seg, F, z, t, h, g0, t, t_end, f, f_new, sc)
        while found == SEARCH_FULL:  # (searched again from the start, with room: the same bracket)
            sc = _grown_search(sc)
            found, outcome, t_reach, t_probe, clear = _event_in_step(seg, F, z, t, h, g0, t, t_end, f, f_new, sc)
        if found and outcome != REACHED:
            return outcome, t_reach, z, h_next, last, nfev, next_sample, t, y_probe, none, False, -1
        while next_sample < sample_times.shape[0] and sample_times[next_sample] <= t_reach:
            dense_at(F, z, t, h, sample_times[next_sample], samples[next_sample])
            next_sample += 1
        if found or moded:
            z_restart = np.empty(_MODE_STATE)
            _dense_all(F, z, t, h, t_reach, z_restart)
            if not found:
                return MODE_EVENT, t_reach, z_restart, h_next, last, nfev, next_sample, t_reach, y_probe, none, \
                    False, which
            dense_at(F, z, t, h, t_probe, y_probe)
            g = sc.g[:n]
            told = clear and g[n - 1] > 0
            return EVENT, t_reach, z_restart, h_next, last, nfev, next_sample, t_probe, y_probe, \
                _positive(seg.ids, g) if told else none, told, -1
        t = t_new
        z[:] = z_new
        f[:] = f_new
        if not riding:
            mode_values(md, t, z, v_lo)
        h_abs = h_next
    return REACHED, t, z, h_abs, last, nfev, next_sample, t, y_probe, none, False, -1


@njit(cache=True)
def ride_data(P, U, w, FL, FC, origin, mus, X, tol):
    """What :class:`~virtual_vehicle.engine.ride.RideStepper` needs of the wheels under a parcel whose centre is at
    ``X`` (m), as :func:`~virtual_vehicle.physics.stick_modes.wheel_arrays` gives them (points, drive directions,
    surface speeds m/s, the support's normal-force map, static coefficients): whether those in contact (``mu_s > 0``,
    ``N > 0``, eq. 19) are one rigid twist of rank 3 to ``tol`` of the speed scale, that twist (vx, vy at ``X``,
    omega), the grip of their zonotope for the centripetal force that twist takes (``g``, ``a``, ``b`` of
    :func:`~virtual_vehicle.physics.stick_modes.zonotope_grip`, each facet's support less rounding) and that force's
    unit direction (zero when it is zero), the farthest wheel (m), the speed scale (m/s) and which wheels are in
    contact."""
    m = P.shape[0]
    N = np.empty(m)
    on = np.zeros(m, np.bool_)
    count = 0
    scale = 1e-3
    for j in range(m):
        N[j] = FL[j, 0] * (X[0] - origin[0]) + FL[j, 1] * (X[1] - origin[1]) + FC[j]  # eq. 19
        on[j] = mus[j] > 0 and N[j] > 0
        count += on[j]
        scale = max(scale, abs(w[j]))
    twist, grip, facing = np.zeros(3), np.zeros(3), np.zeros(2)
    if count < 3:
        return False, twist, grip, facing, 0.0, scale, on
    J, b, G = np.empty((count, 3)), np.empty(count), np.empty((count, 3))
    arm, k = 0.0, 0
    for j in range(m):
        if on[j]:
            rx, ry = P[j, 0] - X[0], P[j, 1] - X[1]
            J[k, 0], J[k, 1], J[k, 2] = U[j, 0], U[j, 1], rx * U[j, 1] - ry * U[j, 0]  # [u, r x u]
            b[k] = w[j]
            bound = mus[j] * N[j]
            for e in range(3):
                G[k, e] = bound * J[k, e]
            arm = max(arm, math.sqrt(rx * rx + ry * ry))
            k += 1
    nu, _, rank, _ = np.linalg.lstsq(J, b)
    if rank < 3:
        return False, twist, grip, facing, arm, scale, on
    for a in range(count):
        if abs(J[a, 0] * nu[0] + J[a, 1] * nu[1] + J[a, 2] * nu[2] - b[a]) > tol * scale:
            return False, twist, grip, facing, arm, scale, on  # not one rigid twist
    size = 0.0
    for a in range(count):
        size += abs(G[a, 0]) + abs(G[a, 1]) + abs(G[a, 2])
    fx, fy = -nu[2] * nu[1], nu[2] * nu[0]  # omega x v: the centripetal force's direction (eq. 3's m a)
    f = math.sqrt(fx * fx + fy * fy)
    if f > 0:
        facing[0], facing[1] = fx / f, fy / f
    g, ga, gb = zonotope_grip(G, facing, 1e-9 * size)
    if not g < np.inf:
        return False, nu, grip, facing, arm, scale, on
    grip[0], grip[1], grip[2] = g, ga, gb
    return True, nu, grip, facing, arm, scale, on


@njit(cache=True)
def ride_measure(points, order, start, lo0, lo1, size, nx, ny, present, positions, wheel_active, directions, V,
                 idx, Y, reach, buffer, noise, noise_force, mu, mu_s, kind, half, normals, n_edges, offsets,
                 vertices, n_vertices, known, support, n_support, holding, spring_lin, force_lin, force_const, origin,
                 on_was, tol, near, n_near, measures, flags, on_now):
    """The anchors and ride data of many parcels in one call, where each parcel's last anchor still stands: for parcel
    ``idx[k]`` (plant index, state ``Y[k]``) whose last anchor is ``known`` (its solution the first of its pattern's
    shared ones), the cells present within ``reach`` (m) of its centre (``_within``, the grid's arrays), their
    footprint margins (:func:`cell_margins`, the parcel's outline padded: ``kind``, ``half``, ``normals`` /
    ``offsets`` (``n_edges`` of them), ``vertices`` (``n_vertices``)); when the cells under it are the anchor's
    (``support``, ``n_support``) and its solution (``holding``: the packed holding test, ``spring_lin``,
    ``force_lin``, ``force_const``, ``origin``, padded by support row) holds at the centre, it is the anchor the
    engine's :func:`~virtual_vehicle.engine.batch.anchor` measures there (the same solution, the same arithmetic):
    writes its near cells (``near``, ``n_near``: the row's width bounds them), ``measures[k]`` = clear, slack (m),
    the wheels' twist (vx, vy m/s, omega rad/s), grip (g, a, b) and the force's direction (2,), arm (m), speed scale
    (m/s) as
    :func:`ride_data` gives them for its wheels (``V`` the contact layer's velocities, m/s; ``mu`` / ``mu_s`` the
    parcel's coefficients), and ``flags[k]`` = measured here, rides (rank 3, one rigid twist), wheels in contact as
    ``on_was`` (the new ones in ``on_now[k]``; its width bounds the wheels too). ``noise`` (m) and ``noise_force``
    (N) are the anchor's rounding noise. A parcel not measured here (flag 0 False) goes to the anchor made in
    Python."""
    for k in range(idx.shape[0]):
        i = idx[k]
        flags[k, 0] = flags[k, 1] = flags[k, 2] = False
        if not known[i]:
            continue
        y = Y[k]
        ids = _within(points, order, start, lo0, lo1, size, nx, ny, present, y[0], y[1], reach[i])
        if ids.shape[0] > near.shape[1]:
            continue  # wider than the columns: the Python anchor widens them
        margins, nearest = cell_margins(kind[i], half[i], normals[i, :n_edges[i]], offsets[i, :n_edges[i]],
                                        vertices[i, :n_vertices[i]], positions[ids], y)
        m = n_support[i]
        count, same = 0, True
        for c in range(ids.shape[0]):
            if margins[c] > 0:
                if count >= m or ids[c] != support[i, count]:
                    same = False
                    break
                count += 1
        if not same or count != m:
            continue  # the cells under it changed: a new anchor
        xi0, xi1 = y[0] - origin[i, 0], y[1] - origin[i, 1]
        p = holding[i]
        if not _holds_packed(p, xi0, xi1):
            continue
        mm, r, q = int(p[0]), int(p[1]), int(p[2])
        at = 3
        basis = p[at:at + mm * r].copy().reshape((mm, r))
        at += mm * r
        plane_lin = p[at:at + 2 * r].copy().reshape((r, 2))
        at += 2 * r
        plane_const = p[at:at + r].copy()
        at += r + mm  # (the contact mask)
        hull_normals = p[at:at + 2 * q].copy().reshape((q, 2))
        at += 2 * q
        hull_offsets = p[at:at + q].copy()
        slack = support_slack(basis, plane_lin, plane_const, spring_lin[i, :m], hull_normals, hull_offsets, xi0, xi1,
                              noise_force[i], noise[i])
        cells = support[i, :m].copy()
        P, U, w, _, _, FL, FC, o, mus, _ = _wheel_arrays(wheel_active, directions, positions, V, cells,
                                                          force_lin[i, :m].copy(), force_const[i, :m].copy(),
                                                          origin[i].copy(), mu[i], mu_s[i])
        if P.shape[0] > on_now.shape[1]:
            continue
        X = np.empty(2)
        X[0], X[1] = y[0], y[1]
        rides, twist, grip, facing, arm, scale, on = ride_data(P, U, w, FL, FC, o, mus, X, tol)
        for c in range(ids.shape[0]):
            near[k, c] = ids[c]
        n_near[k] = ids.shape[0]
        measures[k, 0] = min(buffer[i], nearest) - noise[i]
        measures[k, 1] = slack
        measures[k, 2], measures[k, 3], measures[k, 4] = twist[0], twist[1], twist[2]
        measures[k, 5], measures[k, 6], measures[k, 7] = grip[0], grip[1], grip[2]
        measures[k, 8], measures[k, 9], measures[k, 10], measures[k, 11] = facing[0], facing[1], arm, scale
        flags[k, 0], flags[k, 1] = True, rides
        same_on = on.shape[0] <= on_was.shape[1]
        for j in range(on.shape[0]):
            if same_on and on_was[i, j] != on[j]:
                same_on = False
            on_now[k, j] = on[j]
        flags[k, 2] = same_on
    return 0


# The support-set cache as arrays, and one parcel's event loop over it (issue 32 item 4).
#
# A table (one tuple of arrays, :data:`TABLE_FIELDS`) holds what a parcel's model has solved, as its compiled event
# loop (:func:`run_events`) reads it:
# - records: solved supports (:class:`~virtual_vehicle.physics.contact.SupportSolution` arrays, in their own local
#   coordinates), ``srec`` (R, 6) their offset in ``fpool``, m (cells), r (plane rank), q (hull facets), the length of
#   the packed holding test, and the next record of the same pattern (-1: none);
# - pieces: ``psol`` (P,) a piece's record, ``porigin`` (P, 2) its local origin (m), ``rows`` (P, k) its constants
#   row, ``pnext`` (P,) the next piece of the same support set (-1: none), ``pkey`` (P,) its support set;
# - support sets by their cell ids, patterns by their cells' integer offsets (:func:`pattern`): open-addressing hash
#   ``slots`` / ``gslots`` (a power of two long, -1 empty) into ``kmeta`` (., 4) / ``gmeta`` (., 5): the ids' offset
#   and length in ``ipool``, the first and last piece (record) of the chain, and for a pattern 1 if the model holds
#   solutions of it apart from the shared ones (collinear contact sets: the loop then never solves it);
# - ``used`` (6,): pieces, support sets, ``fpool``, ``ipool`` entries, records, patterns in use.
# A record's floats: weight, basis (m, r), plane_lin (r, 2), plane_const (r,), hull_normals (q, 2), hull_offsets
# (q,), spring_lin (m, 2), spring_gradient (m,), points (m, 2), force_lin (m, 2), force_const (m,), the holding test.
TABLE_FIELDS = ("slots", "kmeta", "ipool", "psol", "porigin", "pnext", "pkey", "rows", "srec", "fpool", "gslots",
                "gmeta", "used")

# Outcomes of run_events besides run_piece's (REACHED, PAUSED, FAILED, NOT_FINITE, NO_CONVERGENCE)
LOOP_MISS, LOOP_SEGMENT, LOOP_CHATTER, LOOP_DONE, LOOP_TOO_MANY = 10, 11, 12, 13, 14
U_PIECES, U_KEYS, U_FLOATS, U_IDS, U_RECORDS, U_PATTERNS = 0, 1, 2, 3, 4, 5


@leaf
def _ids_hash(ids):
    """A hash of integers (FNV-1a over them, wrapping in 64 bits)."""
    h = np.uint64(14695981039346656037)
    for i in range(ids.shape[0]):
        h = (h ^ np.uint64(ids[i])) * np.uint64(1099511628211)
    return h


@leaf
def table_find(slots, meta, ipool, ids):
    """The index of the key ``ids`` ((n,) int64) in hash ``slots`` over ``meta``, or -1."""
    mask = np.uint64(slots.shape[0] - 1)
    s = _ids_hash(ids) & mask
    n = ids.shape[0]
    while True:
        k = slots[s]
        if k < 0:
            return -1
        if meta[k, 1] == n:
            off = meta[k, 0]
            same = True
            for i in range(n):
                if ipool[off + i] != ids[i]:
                    same = False
                    break
            if same:
                return k
        s = (s + np.uint64(1)) & mask


@leaf
def _free_slot(slots, ids):
    mask = np.uint64(slots.shape[0] - 1)
    s = _ids_hash(ids) & mask
    while slots[s] >= 0:
        s = (s + np.uint64(1)) & mask
    return s


@leaf
def table_rehash(slots, meta, ipool, keys):
    """Put the first ``keys`` keys of ``meta`` into the empty ``slots`` (all -1), a larger hash's."""
    for k in range(keys):
        off, n = meta[k, 0], meta[k, 1]
        slots[_free_slot(slots, ipool[off:off + n])] = k


@leaf
def table_add_key(slots, meta, ipool, used, which, ids):
    """Add the key ``ids`` (not there; room for it) to ``slots``/``meta`` (``which`` its count in ``used``) with an
    empty chain; its index."""
    k, off = used[which], used[U_IDS]
    n = ids.shape[0]
    _put_flat(ipool, off, ids)
    meta[k, 0], meta[k, 1], meta[k, 2], meta[k, 3] = off, n, -1, -1
    slots[_free_slot(slots, ids)] = k
    used[which] += 1
    used[U_IDS] += n
    return k


@leaf
def _put_flat(fpool, k, a):
    for i in range(a.shape[0]):
        fpool[k + i] = a[i]
    return k + a.shape[0]


@leaf
def _put_rows(fpool, k, a):
    """A 2-d array's entries into ``fpool`` from ``k``, row by row (as ``a.ravel()``); the end."""
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            fpool[k] = a[i, j]
            k += 1
    return k


@leaf
def record_floats(m, r, q, holding):
    """Entries of ``fpool`` one record of m cells, plane rank r, q hull facets and a holding test this long takes."""
    return 1 + m * r + 3 * r + 3 * q + 8 * m + holding


@leaf
def table_add_record(srec, fpool, used, weight, basis, plane_lin, plane_const, hull_normals, hull_offsets, spring_lin,
                     spring_gradient, points, force_lin, force_const, holding):
    """Append a record of these solution arrays (C-contiguous; room for it), copied value for value; its index."""
    j, off = used[U_RECORDS], used[U_FLOATS]
    (m, r), q = basis.shape, hull_offsets.shape[0]
    fpool[off] = weight
    end = _put_rows(fpool, off + 1, basis)
    end = _put_rows(fpool, end, plane_lin)
    end = _put_flat(fpool, end, plane_const)
    end = _put_rows(fpool, end, hull_normals)
    end = _put_flat(fpool, end, hull_offsets)
    end = _put_rows(fpool, end, spring_lin)
    end = _put_flat(fpool, end, spring_gradient)
    end = _put_rows(fpool, end, points)
    end = _put_rows(fpool, end, force_lin)
    end = _put_flat(fpool, end, force_const)
    end = _put_flat(fpool, end, holding)
    srec[j, 0], srec[j, 1], srec[j, 2], srec[j, 3], srec[j, 4], srec[j, 5] = off, m, r, q, holding.shape[0], -1
    used[U_RECORDS] += 1
    used[U_FLOATS] = end
    return j


@leaf
def table_chain_record(srec, gmeta, g, j):
    """Append record ``j`` to the chain of pattern ``g``."""
    if gmeta[g, 3] < 0:
        gmeta[g, 2] = j
    else:
        srec[gmeta[g, 3], 5] = j
    gmeta[g, 3] = j


@leaf
def table_add_piece(kmeta, psol, porigin, pnext, pkey, rows, used, k, j, origin, row):
    """Append a piece of record ``j`` at local origin ``origin`` (m) with constants ``row`` to the chain of support
    set ``k`` (room for it); its index."""
    p = used[U_PIECES]
    psol[p], pkey[p], pnext[p] = j, k, -1
    porigin[p, 0], porigin[p, 1] = origin[0], origin[1]
    for i in range(row.shape[0]):
        rows[p, i] = row[i]
    if kmeta[k, 3] < 0:
        kmeta[k, 2] = p
    else:
        pnext[kmeta[k, 3]] = p
    kmeta[k, 3] = p
    used[U_PIECES] += 1
    return p


@leaf
def table_add_piece_of(slots, kmeta, ipool, psol, porigin, pnext, pkey, rows, used, ids, j, origin, row):
    """:func:`table_add_piece` to the chain of support set ``ids``, added first if it is not there (room for
    both), in one call (a miss took four); the piece's index."""
    k = table_find(slots, kmeta, ipool, ids)
    if k < 0:
        k = table_add_key(slots, kmeta, ipool, used, U_KEYS, ids)
    return table_add_piece(kmeta, psol, porigin, pnext, pkey, rows, used, k, j, origin, row)


@njit(cache=True)
def piece_segment(srec, fpool, j, origin, kind, convex, half, normals, offsets, vertices, candidates, center, buffer,
                  reach, noise_length, noise_force, ids):
    """The segment fields :func:`run_piece` and the mode loop take for a piece whose solution is the table's record
    ``j`` (its local origin ``origin``, m): the footprint's and candidates' fields with the record's plane, hull and
    spring arrays."""
    _, basis, plane_lin, plane_const, hull_normals, hull_offsets, spring_lin, spring_gradient, _, _, _, _ = \
        _record_arrays(srec, fpool, j)
    return (kind, convex, half, normals, offsets, vertices, candidates, origin, basis, plane_lin, plane_const,
            hull_normals, hull_offsets, center, buffer, reach, noise_length, noise_force, spring_lin, spring_gradient,
            ids)


@njit(cache=True)
def _record_arrays(srec, fpool, j):
    """Record ``j``'s arrays as views of ``fpool``: weight, basis, plane_lin, plane_const, hull_normals,
    hull_offsets, spring_lin, spring_gradient, points, force_lin, force_const, holding."""
    off, m, r, q, nh = srec[j, 0], srec[j, 1], srec[j, 2], srec[j, 3], srec[j, 4]
    weight = fpool[off]
    off += 1
    basis = fpool[off:off + m * r].reshape((m, r))
    off += m * r
    plane_lin = fpool[off:off + 2 * r].reshape((r, 2))
    off += 2 * r
    plane_const = fpool[off:off + r]
    off += r
    hull_normals = fpool[off:off + 2 * q].reshape((q, 2))
    off += 2 * q
    hull_offsets = fpool[off:off + q]
    off += q
    spring_lin = fpool[off:off + 2 * m].reshape((m, 2))
    off += 2 * m
    spring_gradient = fpool[off:off + m]
    off += m
    points = fpool[off:off + 2 * m].reshape((m, 2))
    off += 2 * m
    force_lin = fpool[off:off + 2 * m].reshape((m, 2))
    off += 2 * m
    force_const = fpool[off:off + m]
    off += m
    holding = fpool[off:off + nh]
    return (weight, basis, plane_lin, plane_const, hull_normals, hull_offsets, spring_lin, spring_gradient, points,
            force_lin, force_const, holding)


@leaf
def _holding_at(srec, j):
    """Where record ``j``'s packed holding test lies in the float pool: its first entry, and the one after it."""
    off = srec[j, 0] + record_floats(srec[j, 1], srec[j, 2], srec[j, 3], 0)
    return off, off + srec[j, 4]


@njit(cache=True)
def _holding_of(srec, fpool, j):
    start, end = _holding_at(srec, j)
    return fpool[start:end]


@leaf
def _record_holds(srec, fpool, j, x, y):
    """Whether record ``j``'s contact set and hull hold at (x, y) (m, in its local coordinates)."""
    start, end = _holding_at(srec, j)
    return _holds_packed(fpool[start:end], x, y)


@leaf
def table_lookup(tab, ids, x, y):
    """The first piece of support set ``ids`` whose contact set and hull hold at centre of mass (x, y) (m), as
    :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.piece_for` tries its cached pieces; -1 for none, -2 for a
    support set the table does not know."""
    slots, kmeta, ipool, psol, porigin, pnext, pkey, rows, srec, fpool, gslots, gmeta, used = tab
    k = table_find(slots, kmeta, ipool, ids)
    if k < 0:
        return -2
    p = kmeta[k, 2]
    while p >= 0:
        if _record_holds(srec, fpool, psol[p], x - porigin[p, 0], y - porigin[p, 1]):
            return p
        p = pnext[p]
    return -1


DRIVES = (None, ViscousLaw.drive_kernel, CoulombLaw.drive_kernel)
"""The compiled drives (:attr:`~virtual_vehicle.physics.laws.base.FrictionLaw.drive_kernel`) the event loop can
call, by their code (:func:`drive_code`; 0: none, the loop makes no pieces). A function passed as an argument
instead cost ~20 us a call to type (numba has no fast path for it)."""
_viscous_drive, _coulomb_drive = DRIVES[1], DRIVES[2]


def drive_code(law) -> int:
    """The code in :data:`DRIVES` of ``law``'s compiled drive, 0 for none the loop knows."""
    kernel = getattr(law, "drive_kernel", None)
    return next((code for code, known in enumerate(DRIVES) if code and known is kernel), 0)


@njit(cache=True)
def _drive(code, V, U):
    if code == 2:
        return _coulomb_drive(V, U)
    return _viscous_drive(V, U)


@njit(cache=True)
def _gather(a, ids):
    out = np.empty((ids.shape[0],) + a.shape[1:])
    for i in range(ids.shape[0]):
        out[i] = a[ids[i]]
    return out


@njit(cache=True)
def _solve_into(tab, pts, rel, flat, g, x, y, unit, weight, solve_log, solve_origin):
    """:func:`table_from_pattern`'s solve of the pattern ``rel`` (key ``flat``; ``g`` its index, -1 if new) of cells at
    ``pts`` for a centre of mass at (x, y) (m): the new record's index, or -1 (see there)."""
    slots, kmeta, ipool, psol, porigin, pnext, pkey, rows, srec, fpool, gslots, gmeta, used = tab
    m, s = pts.shape[0], solve_log[0, 1]
    if (solve_log[0, 0] != 1 or (g >= 0 and gmeta[g, 4] != 0) or s >= solve_origin.shape[0]
            or used[U_RECORDS] >= srec.shape[0] or used[U_PATTERNS] >= gmeta.shape[0]
            or 2 * (used[U_PATTERNS] + 1) > gslots.shape[0] or used[U_IDS] + 3 * m > ipool.shape[0]
            or used[U_FLOATS] + record_floats(m, 3, m, 3 + 4 * m + 9 + 3 * m) > fpool.shape[0]):
        return -1
    local_pts = np.empty((m, 2))  # the pattern's own coordinates, its first cell at the local origin
    for i in range(m):
        local_pts[i, 0], local_pts[i, 1] = rel[i, 0] * unit, rel[i, 1] * unit
    com = np.empty(2)
    com[0], com[1] = x - pts[0, 0], y - pts[0, 1]
    (status, origin, points, _, basis, plane_lin, plane_const, hull_normals, hull_offsets, spring_lin,
     spring_gradient, holding, force_lin, force_const) = solve_planar_kernel(local_pts, com, weight, _MAX_ITER)
    if status != SOLVED:
        return -1
    j = table_add_record(srec, fpool, used, weight, basis, plane_lin, plane_const, hull_normals, hull_offsets,
                         spring_lin, spring_gradient, points, force_lin, force_const, holding)
    if g < 0:
        g = table_add_key(gslots, gmeta, ipool, used, U_PATTERNS, flat)
    table_chain_record(srec, gmeta, g, j)
    solve_log[1 + s, 0], solve_log[1 + s, 1] = j, g
    solve_origin[s, 0], solve_origin[s, 1] = origin[0], origin[1]
    solve_log[0, 1] = s + 1
    return j


@njit(cache=True)
def table_from_pattern(tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping, inv_mass,
                       inv_inertia, born_terms, born, weight, solve_log, solve_origin):
    """A new piece for the support set ``ids``, which the table (and the model it mirrors) has never met, from a
    solved pattern that holds at centre of mass (x, y) (m), as
    :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.solution_for` finds it in its shared store (a translated
    copy) and the law's :meth:`~virtual_vehicle.physics.laws.base.FrictionLaw.constants_and_row` makes its constants
    (eqs. 23, 29, 33, 38: :func:`~virtual_vehicle.physics.laws.affine._terms_and_row` of the law's compiled drive
    vectors of ``velocities[ids]`` and ``directions[ids]``, ``drive`` its code in :data:`DRIVES`). Its packed terms
    go to ``born_terms[born]``.

    Where no solved pattern holds, the pattern is solved here (:func:`~virtual_vehicle.physics.contact.
    solve_planar_kernel`, the arithmetic of the Python solve, in the pattern's own coordinates as
    :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.solution_for` solves it, for a parcel of ``weight`` N) when
    ``solve_log[0, 0]`` is 1 (the table mirrors the model's whole store, so that Python would solve too), the pattern
    has no solution of its own (``gmeta[g, 4]``: a collinear contact set, which Python keeps apart) and there is room:
    the record is added and chained to its pattern, and ``solve_log[1 + s]`` (record, pattern) and
    ``solve_origin[s]`` (its local origin, m) say what was solved, ``s = solve_log[0, 1]`` counting them, for Python
    to add to the model's store after the call. -1 where Python must act: the solve's outcome is not ``SOLVED``
    (supports on one line, tipping, a collinear contact set), or no room."""
    slots, kmeta, ipool, psol, porigin, pnext, pkey, rows, srec, fpool, gslots, gmeta, used = tab
    m = ids.shape[0]
    if (m == 0 or born >= born_terms.shape[0] or used[U_PIECES] >= psol.shape[0] or used[U_KEYS] >= kmeta.shape[0]
            or 2 * (used[U_KEYS] + 1) > slots.shape[0] or used[U_IDS] + m > ipool.shape[0]):
        return -1
    pts, origin, rel = pattern(positions, ids, unit)
    flat = rel.ravel()
    g = table_find(gslots, gmeta, ipool, flat)
    xi0, xi1 = x - origin[0], y - origin[1]
    j = -1
    if g >= 0:
        j = gmeta[g, 2]
        while j >= 0 and not _record_holds(srec, fpool, j, xi0, xi1):
            j = srec[j, 5]
    if j < 0:
        j = _solve_into(tab, pts, rel, flat, g, x, y, unit, weight, solve_log, solve_origin)
        if j < 0:
            return -1
    weight, _, _, _, _, _, _, _, points, force_lin, force_const, _ = _record_arrays(srec, fpool, j)
    out = _terms_and_row(points, _drive(drive, _gather(velocities, ids), _gather(directions, ids)), force_lin,
                         force_const, mu, damping, weight, origin, inv_mass, inv_inertia)
    k = table_add_key(slots, kmeta, ipool, used, U_KEYS, ids)
    born_terms[born, :] = out[:born_terms.shape[1]]
    return table_add_piece(kmeta, psol, porigin, pnext, pkey, rows, used, k, j, origin, out[born_terms.shape[1]:])


@njit(cache=True)
def _in_contact(srec, fpool, j):
    """Record ``j``'s contact mask (1.0 in contact), as its holding test packs it."""
    holding = _holding_of(srec, fpool, j)
    m, r = int(holding[0]), int(holding[1])
    return holding[3 + m * r + 3 * r:3 + m * r + 3 * r + m]


@njit(cache=True)
def table_piece_again(tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping, inv_mass,
                      inv_inertia, born_terms, born, weight, solve_log, solve_origin):
    """The piece of the support set ``ids``, which the table knows but none of whose pieces holds at centre of mass
    (x, y) (m), as :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.piece_for` finds it then: the first solution
    of its pattern that holds (or solved here), as :func:`~virtual_vehicle.engine._kernel.table_from_pattern` finds
    it; a piece of the set with the same contact set if there is one (Python's cache keeps that one), else a new
    piece at the end of the set's chain (its packed terms to ``born_terms[born]``). Returns (piece, whether it is
    new); -1 where Python must act (as table_from_pattern)."""
    slots, kmeta, ipool, psol, porigin, pnext, pkey, rows, srec, fpool, gslots, gmeta, used = tab
    m = ids.shape[0]
    k = table_find(slots, kmeta, ipool, ids)
    if m == 0 or k < 0 or born >= born_terms.shape[0] or used[U_PIECES] >= psol.shape[0]:
        return -1, False
    pts, origin, rel = pattern(positions, ids, unit)
    flat = rel.ravel()
    g = table_find(gslots, gmeta, ipool, flat)
    j = -1
    if g >= 0:
        j = gmeta[g, 2]
        while j >= 0 and not _record_holds(srec, fpool, j, x - origin[0], y - origin[1]):
            j = srec[j, 5]
    if j < 0:
        j = _solve_into(tab, pts, rel, flat, g, x, y, unit, weight, solve_log, solve_origin)
        if j < 0:
            return -1, False
    mine = _in_contact(srec, fpool, j)
    p = kmeta[k, 2]
    while p >= 0:
        theirs = _in_contact(srec, fpool, psol[p])
        same = theirs.shape[0] == m
        for i in range(m):
            same = same and (theirs[i] > 0.5) == (mine[i] > 0.5)
        if same:
            return p, False
        p = pnext[p]
    weight, _, _, _, _, _, _, _, points, force_lin, force_const, _ = _record_arrays(srec, fpool, j)
    out = _terms_and_row(points, _drive(drive, _gather(velocities, ids), _gather(directions, ids)), force_lin,
                         force_const, mu, damping, weight, origin, inv_mass, inv_inertia)
    born_terms[born, :] = out[:born_terms.shape[1]]
    return table_add_piece(kmeta, psol, porigin, pnext, pkey, rows, used, k, j, origin,
                           out[born_terms.shape[1]:]), True


@njit(cache=True)
def table_next_piece(tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping, inv_mass,
                     inv_inertia, born_terms, born, weight, solve_log, solve_origin):
    """The piece of support set ``ids`` at centre of mass (x, y) (m), as
    :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.piece_for` finds it: the table's (:func:`table_lookup`), else
    made from a solved pattern for a set it has never met (:func:`table_from_pattern`) or for one it met on other
    contact sets (:func:`table_piece_again`), with a drive only. Returns (piece or < 0 where Python must act, pieces
    born so far: ``born`` plus one for a piece made here)."""
    q = table_lookup(tab, ids, x, y)
    if q >= 0:
        return q, born
    return table_new_piece(q, tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping, inv_mass,
                           inv_inertia, born_terms, born, weight, solve_log, solve_origin)


@njit(cache=True)
def table_new_piece(missing, tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping, inv_mass,
                    inv_inertia, born_terms, born, weight, solve_log, solve_origin):
    """:func:`table_next_piece` past its lookup, whose answer ``missing`` is -2 (a support set the table does not
    know) or -1 (none of its pieces holds): the piece made, as there (the event loop looks up with the leaf alone,
    and calls this, whose arguments are counted, only for a piece it must make)."""
    q = missing
    if q == -2 and drive:
        q = table_from_pattern(tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping, inv_mass,
                               inv_inertia, born_terms, born, weight, solve_log, solve_origin)
        if q >= 0:
            born += 1
    elif q == -1 and drive:
        q, made = table_piece_again(tab, ids, x, y, positions, unit, velocities, directions, drive, mu, damping,
                                    inv_mass, inv_inertia, born_terms, born, weight, solve_log, solve_origin)
        if made:
            born += 1
    return q, born


@njit(cache=True)
def cells_under(grid, positions, kind, half, normals, offsets, vertices, y):
    """Ids of the cells under the footprint (``kind`` ... ``vertices``: an :func:`outline`'s entries less ``convex``)
    at state ``y``, as :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.support_at` finds them: the cells present
    within the radius (to rounding) of the centre (``grid`` as :func:`run_events` takes it, ``positions`` the cells'),
    those of positive margin (:func:`cell_margins`)."""
    (g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, radius) = grid
    near = _within(g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, y[0], y[1],
                   radius * (1 + 1e-9) + 1e-12)
    margins, _ = cell_margins(kind, half, normals, offsets, vertices, _gather(positions, near), y)
    return near[margins > 0]


@njit(cache=True)
def run_events(tab, fields, p, begin, y_base, t, y, t_bound, h, h_abs, first_step, rtol, atol, max_step, max_steps,
               sample_times, next_sample, samples, segments, max_segments, ring_t, ring_p, ring, chatter_span,
               chatter_pieces, ev_t, ev_y, ev_p, law, grid):
    """One parcel's event loop over the table ``tab``: :func:`run_piece` on piece ``p`` (its segment the candidates,
    centre and scales of ``fields``, a :func:`make_segment` tuple, with the piece's own solution), and at each event the
    next piece from the table, or made from a solved pattern (:func:`table_from_pattern`, ``law`` its arguments after
    the centre of mass, the drive's code first; none when that is 0), until Python must act. With ``begin`` the piece
    begins at probe ``y_base`` (a support change Python found: the candidates kept if they still cover it, else
    ``LOOP_SEGMENT``); without, it goes on from ``y_base`` with ``first_step`` (a segment Python began, or a pause).
    Arguments as :func:`run_piece`'s, and: ``h`` the last step taken (s: a new piece's first step is ``min(h, t_bound -
    t)``), ``segments`` the pieces begun so far (at most ``max_segments``), ``ring_t``/``ring_p`` (c,) and ``ring`` (2,)
    the latest events' times and pieces (count, next slot) for the chatter test (``c`` events within ``chatter_span`` s
    times max(1, |t|) among at most ``chatter_pieces`` pieces), ``max_steps`` also the pieces it begins in one call
    (the next is Python's to begin: a progress callback hears of the run at least that often), ``ev_t`` (E,), ``ev_y``
    (E, 6), ``ev_p`` (E, 2) where
    the support changes are written (time, restart state, piece before and after), ``grid`` what gathers the
    candidates again where Python's :class:`~virtual_vehicle.engine.dynamics._Segment` would (a new piece clearly
    beyond half the buffer from where they were gathered): the cells' ``PointGrid`` arrays (points, order, start, lo
    x, lo y, bucket size, buckets across, buckets up), the ``present`` mask (empty: all) and the parcel's radius (m).

    Returns (outcome, t, y, piece, h, h_abs, evaluations, next_sample, segments, events written, pieces made,
    probe state, cells under the footprint at the probe, whether those tell, then the candidates' ids, positions
    and centre as they are now). Outcomes: ``REACHED`` (t_bound),
    ``PAUSED`` (``max_steps`` steps on the current piece: resume it with ``first_step`` 0), a failure,
    ``LOOP_DONE`` (an event at t_bound: the new piece written), ``LOOP_MISS`` (an event whose next piece the table
    cannot give nor make: a solve it cannot make (supports on one line, a collinear contact set, tipping, a pattern
    with solutions of the model's own, a store it does not mirror) or no room; the cells under the footprint at the
    probe come with it, found as :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.support_at` finds them
    (:func:`cells_under`) where the probe's values do not tell them), ``LOOP_CHATTER`` (the chatter test held at
    this event; its ring to be cleared), ``LOOP_SEGMENT`` (a new piece begins within a rounding step of the
    threshold of gathering its candidates again, the event columns are full or ``max_steps`` pieces were begun:
    Python begins the segment), ``LOOP_TOO_MANY`` (more than ``max_segments`` pieces).

    At a support event the next piece is the table's (:func:`table_lookup`), or made from a solved pattern for a
    support set the table has never met (:func:`table_from_pattern`) or for one it met on other contact sets
    (:func:`table_piece_again`), as :meth:`~virtual_vehicle.engine.dynamics.ParcelModel.piece_for` would find or
    make it."""
    kind, convex, half, normals, offsets, vertices, candidates = (fields[0], fields[1], fields[2], fields[3],
                                                                 fields[4], fields[5], fields[6])
    center, buffer, reach, noise_length, noise_force, ids = (fields[13], fields[14], fields[15], fields[16],
                                                             fields[17], fields[20])
    (drive, positions, unit, velocities, directions, mu, damping, inv_mass, inv_inertia, born_terms, weight, solve_log,
     solve_origin) = law
    psol, porigin, rows, srec, fpool = tab[3], tab[4], tab[7], tab[8], tab[9]
    reuse2 = 0.25 * buffer * buffer * (1.0 - 1e-9)  # clearly within half the buffer (the edge is Python's to decide)
    gather2 = 0.25 * buffer * buffer * (1.0 + 1e-9)  # clearly beyond it: gathered again, as _Segment would
    (g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, radius) = grid
    capacity, ring_size = ev_t.shape[0], ring_t.shape[0]
    n_ev = born = nfev = begun = 0
    y_probe = y_base
    none = np.empty(0, np.int64)
    sc = search_scratch(0)  # (made for the first piece's values, then kept)
    base = np.empty(6)
    while True:
        if begin:  # a new piece: its candidates kept while clearly within half the buffer of where they were gathered
            dx, dy = y_probe[0] - center[0], y_probe[1] - center[1]
            d2 = dx * dx + dy * dy
            if n_ev == capacity or begun == max_steps or not (d2 < reuse2 or d2 > gather2):
                return (LOOP_SEGMENT, t, y, p, h, h_abs, nfev, next_sample, segments, n_ev, born, y_probe, none,
                        False, ids, candidates, center)
            if not d2 < reuse2:  # the cells within the radius plus the buffer of the probe (PointGrid.within)
                ids = _within(g_points, g_order, g_start, g_lo0, g_lo1, g_size, g_nx, g_ny, present, y_probe[0],
                              y_probe[1], radius + buffer)
                candidates = _gather(positions, ids)
                center = np.empty(2)
                center[0], center[1] = y_probe[0], y_probe[1]
            segments += 1
            begun += 1
            if segments > max_segments:
                return (LOOP_TOO_MANY, t, y, p, h, h_abs, nfev, next_sample, segments, n_ev, born, y_probe, none,
                        False, ids, candidates, center)
            base[:] = y_probe  # (the probe's view is written again at the piece's event)
            y_base = base
            first_step, h_abs = min(h, t_bound - t), 0.0
        begin = True
        seg = Segment(*piece_segment(srec, fpool, psol[p], porigin[p], kind, convex, half, normals, offsets,
                                     vertices, candidates, center, buffer, reach, noise_length, noise_force, ids))
        n = n_values(seg)
        if sc.G.shape[1] < n:
            sc = search_scratch(2 * n)
        while True:
            (outcome, t, h_abs, last, evals, next_sample, t_probe, n_under,
             told) = _piece(rows[p], seg, y_base, t, y, t_bound, h_abs, first_step, rtol, atol, max_step, max_steps,
                            sample_times, next_sample, samples, sc)
            nfev += evals
            if last:
                h = last
            if outcome != SEARCH_OUT:
                break
            y, first_step, sc = sc.state.copy(), 0.0, _grown_search(sc)
        # (views of the scratch: the next piece reads them before it writes it, and a new call makes its own)
        y, y_probe, under = sc.state, sc.probe, sc.under[:n_under]
        if outcome != EVENT:
            return (outcome, t, y, p, h, h_abs, nfev, next_sample, segments, n_ev, born, y_base, none, False, ids,
                    candidates, center)
        # the chatter test over the latest events (the piece each ended)
        ring_t[ring[1]], ring_p[ring[1]] = t, p
        ring[1] = (ring[1] + 1) % ring_size
        ring[0] = min(ring[0] + 1, ring_size)
        if ring[0] == ring_size and t - ring_t[ring[1]] < chatter_span * max(1.0, abs(t)):
            distinct = 0
            seen = np.full(chatter_pieces + 1, -1, np.int64)
            for j in range(ring_size):
                known = False
                for i in range(distinct):
                    known = known or seen[i] == ring_p[j]
                if not known:
                    seen[distinct] = ring_p[j]
                    distinct += 1
                    if distinct > chatter_pieces:
                        break
            if distinct <= chatter_pieces:
                return (LOOP_CHATTER, t, y, p, h, h_abs, nfev, next_sample, segments, n_ev, born, y_probe, under,
                        told, ids, candidates, center)
        if not told:  # the probe's values do not tell: the cells under the footprint found as support_at finds them
            under, told = cells_under(grid, positions, kind, half, normals, offsets, vertices, y_probe), True
        q = table_lookup(tab, under, y_probe[0], y_probe[1])
        if q < 0:
            q, born = table_new_piece(q, tab, under, y_probe[0], y_probe[1], positions, unit, velocities, directions,
                                      drive, mu, damping, inv_mass, inv_inertia, born_terms, born, weight, solve_log,
                                      solve_origin)
        if q < 0:
            return (LOOP_MISS, t, y, p, h, h_abs, nfev, next_sample, segments, n_ev, born, y_probe, under, told, ids,
                    candidates, center)
        if q != p:
            ev_t[n_ev] = t
            ev_y[n_ev, :] = y
            ev_p[n_ev, 0], ev_p[n_ev, 1] = p, q
            n_ev += 1
        p = q
        if t >= t_bound:
            return (LOOP_DONE, t, y, p, h, h_abs, nfev, next_sample, segments, n_ev, born, y_probe, none, False, ids,
                    candidates, center)
