"""Exact, event-driven stick-slip of one parcel on one fixed support set: modes, their smooth dynamics, their events.

Units: SI (m, s, kg, N, N m, J); a twist is (vx, vy, omega) in m/s, m/s, rad/s.

Each roller wheel is a 1-D friction contact along its drive direction ``u`` (free along its axle). With ``r`` from the
centre of mass to the wheel's contact point its Jacobian row is ``J = [u_x, u_y, r x u]``, its slip speed
``s = J nu - w`` (``w`` the wheel's surface speed along ``u``) and its force on the parcel ``lam`` (N, along ``u``),
``|lam| <= mu N`` with the cell's normal force ``N`` from the support set's affine map (paper eqs. 3-19).

Between events the parcel is in a *mode*: each wheel sticks (``s = 0``) or slips with a known sign ``sigma`` and then
pushes with the kinetic force ``lam = -sigma mu_k N`` (the per-wheel form of the paper's Coulomb law, eqs. 20-22:
a wheel that outruns the parcel pushes it with ``mu N`` along its spin). Sticking wheels are linear constraints on
the acceleration, ``J nu_dot + c = w_dot`` with ``c = -omega (v x u)`` (the lever ``r`` changes as the centre moves,
``dr/dt = -v``); their forces come from the KKT system ``M nu_dot = J^T lam``. Three independent sticking rows fix the
twist: the parcel rides the field rigidly, and the mode then ends only at a support event (the engine's) or where the
wrench that riding takes (zero on a uniform field, centripetal on a turning one) leaves what the wheels can hold.

**Redundant sticking wheels (the rule).** With more than three sticking wheels their forces are not unique, only
their net wrench ``F_S`` is. Stick holds while ``F_S`` lies in the zonotope ``Z_S = {J_S^T lam : |lam_j| <= mu_s N_j}``
(the wrenches the sticking wheels can supply within their static bounds) and breaks when ``F_S`` crosses a facet of
``Z_S``. At that facet every wheel off the facet's plane is at its static bound, so exactly those wheels break and
slip against their force; the wheels in the facet's plane are decided again. This is the rule the fixed-step law
(:mod:`virtual_vehicle.engine.stickslip`) obeys: its box LCP has a unique post-step twist, and that twist sticks iff
the required impulse lies in ``h Z_S``. The per-wheel stick forces reported are the minimum-norm ones (any other
distribution inside the bounds has the same wrench, the same motion and the same power). The stepped law converges
to this at first order through such breaks (tested), also with ``mu_s > mu_k`` since it gives the static bound next
step to every wheel whose slip after the step is zero. (It once judged by the impulse, strictly inside the bound:
its projected Gauss-Seidel may put a redundant sticking wheel exactly at its bound while the wrench is well inside
``h Z_S``; that wheel was then held to ``mu_k`` although it never slid, its zonotope shrank, and the grip broke
early, 3 ms before the exact break on a turning field whatever the step.)

**Deciding a mode (at an event).** Slipping wheels keep their sign. Wheels at zero slip solve the acceleration-level
box problem ``min 1/2 lam^T A lam + q^T lam`` over ``|lam| <= mu_s N`` (``A = J M^-1 J^T``), whose acceleration
``nu_dot`` is unique (the problem is the dual of a strictly convex one in ``nu_dot``). It is solved in two stages:
projected Gauss-Seidel identifies which wheels keep zero slip acceleration (O(sweeps m)), then the mode is solved
exactly (one least-squares KKT solve, O(m^3)) and checked exactly (every sticking wheel's required wrench inside
``Z_S`` by its facets, O(m^3) for m sticking wheels; every breaking wheel accelerating in its slip direction). Wheels
that break slip with the kinetic force, and the rest are decided again with that force known, until none breaks
(at most m rounds; one when ``mu_s = mu_k``). Enumerating the 3^m sign patterns instead would cost 3^24 solves for
a 12-cell footprint.

A stuck wheel (cannot turn) has surface speed 0; a free-spinning wheel (cannot push) has both coefficients 0 and
takes no part (no force, no constraint, no event).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.integrate import solve_ivp

__all__ = ["Wheels", "Mode", "ModeEvent", "StickSlipRun", "wheels_on", "decide_mode", "mode_rhs", "mode_events",
           "simulate", "stick_facets", "breaking_wheels", "project_twist", "wheel_arrays", "arrays_of", "decide_kernel",
           "breaking_kernel", "decide_compiled", "zonotope_inradius", "zonotope_grip", "box_sweeps"]

_SLIP_TOL = 1e-9  # relative to the speed scale: a wheel this close to zero slip is at zero slip
_EPS = float(np.finfo(np.float64).eps)
_TIME_ULPS, _TIME_FLOOR = 16.0, 2e-13  # an event's time is known to 16 eps |t| + 2e-13 s (:func:`_slip_tol`)
_ACCEL_TOL = 1e-7  # relative to the acceleration scale: a slip acceleration this small is zero
_PLANE_TOL = 1e-9  # relative: a generator this close to a facet's plane lies in it


@dataclass(frozen=True, eq=False)
class Wheels:
    """The wheels under a parcel on one support set, each a 1-D friction contact.

    Attributes:
        points: (m, 2) contact points, m (world frame; the cells do not move).
        directions: (m, 2) unit drive directions.
        speeds: (m,) surface speed along the drive direction, m/s, at time ``t0``.
        accels: (m,) its rate, m/s^2 (wheel speeds ramp linearly: ``speeds + accels (t - t0)``).
        t0: s, the time ``speeds`` hold at.
        force_lin, force_const, origin: the support set's normal-force map: the normal force (N) of each wheel's cell
            is ``force_lin @ (X_c - origin) + force_const`` (paper eq. 19 with its contact set).
        mu_static, mu_kinetic: (m,) coefficients; 0 and 0 for a free-spinning wheel.
        keys: per wheel (entry, wheel index) in the cell array it came from.
    """

    points: np.ndarray
    directions: np.ndarray
    speeds: np.ndarray
    accels: np.ndarray
    t0: float
    force_lin: np.ndarray
    force_const: np.ndarray
    origin: np.ndarray
    mu_static: np.ndarray
    mu_kinetic: np.ndarray
    keys: tuple = ()

    def __post_init__(self) -> None:
        m = len(self.points)
        for name, shape in (("points", (m, 2)), ("directions", (m, 2)), ("speeds", (m,)), ("accels", (m,)),
                            ("force_lin", (m, 2)), ("force_const", (m,)), ("origin", (2,)),
                            ("mu_static", (m,)), ("mu_kinetic", (m,))):
            arr = np.array(getattr(self, name), dtype=float)
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
            if not np.isfinite(arr).all():
                raise ValueError(f"{name} must be finite")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        if not np.allclose(np.hypot(*self.directions.T), 1.0, atol=1e-9):
            raise ValueError("drive directions must be unit vectors")
        if (self.mu_kinetic < 0).any() or (self.mu_static < self.mu_kinetic).any():
            raise ValueError("friction coefficients must satisfy 0 <= mu_kinetic <= mu_static")

    @property
    def m(self) -> int:
        """Number of wheels."""
        return len(self.points)

    @property
    def free(self) -> np.ndarray:
        """(m,) True for wheels that cannot push (no friction)."""
        return self.mu_static == 0

    def normal(self, com) -> np.ndarray:
        """(m,) normal force of each wheel's cell (N) for centre of mass ``com`` (m)."""
        return self.force_lin @ (np.asarray(com, dtype=float) - self.origin) + self.force_const

    def rows(self, com) -> np.ndarray:
        """(m, 3) Jacobian rows ``[u_x, u_y, r x u]`` for centre of mass ``com`` (m)."""
        r = self.points - np.asarray(com, dtype=float)
        u = self.directions
        return np.column_stack([u[:, 0], u[:, 1], r[:, 0] * u[:, 1] - r[:, 1] * u[:, 0]])

    def surface(self, t: float) -> np.ndarray:
        """(m,) surface speeds (m/s) at time ``t`` (s)."""
        return self.speeds + self.accels * (t - self.t0)

    def slips(self, t: float, y) -> np.ndarray:
        """(m,) slip speeds ``J nu - w`` (m/s) at time ``t`` and state ``y`` = (x, y, theta, vx, vy, omega)."""
        y = np.asarray(y, dtype=float)
        return self.rows(y[:2]) @ y[3:6] - self.surface(t)


def wheels_on(cells, support, solution, velocities, mu: float, mu_static: float | None = None, *,
              accelerations=None, stuck=None, free=None, t0: float = 0.0) -> Wheels:
    """The :class:`Wheels` of the entries ``support`` ((k,) indices into ``cells``, a
    :class:`~virtual_vehicle.model.layout.CellArray`) whose solved support set is ``solution`` (a
    :class:`~virtual_vehicle.physics.contact.SupportSolution` of ``cells.positions[support]``).

    ``velocities`` (n, 2) m/s are the entries' surface velocities (as a friction law takes them) and ``accelerations``
    (n, 2) m/s^2 their rates (default 0); each present wheel (``cells.wheel_active``) moves at their projection on its
    drive direction. ``mu`` is kinetic, ``mu_static`` (default ``mu``) static. ``stuck`` (n, 2) bool marks wheels that
    cannot turn (surface speed 0; a run's ``Faults.held``), ``free`` (n, 2) bool wheels that cannot push (coefficients
    0; ``Faults.free_wheels``). Every present wheel
    of an entry carries its entry's whole normal force, as in the paper's Coulomb law (eq. 21).
    """
    support = np.asarray(support, dtype=np.int64)
    n = cells.n
    V = np.asarray(velocities, dtype=float)
    A = np.zeros((n, 2)) if accelerations is None else np.asarray(accelerations, dtype=float)
    stuck = np.zeros((n, 2), bool) if stuck is None else np.asarray(stuck, bool)
    free = np.zeros((n, 2), bool) if free is None else np.asarray(free, bool)
    if V.shape != (n, 2) or A.shape != (n, 2) or stuck.shape != (n, 2) or free.shape != (n, 2):
        raise ValueError(f"velocities, accelerations, stuck and free must have shape ({n}, 2)")
    if solution.force_lin.shape != (len(support), 2):
        raise ValueError("the support solution must be that of the supporting entries, in their order")
    mu_s = mu if mu_static is None else mu_static
    row, k = np.nonzero(cells.wheel_active[support])  # each entry's wheels in order (one array pass: at every event)
    i = support[row]
    u = cells.drive_directions[i, k]
    held, loose = stuck[i, k], free[i, k]
    return Wheels(points=cells.positions[i], directions=u,
                  speeds=np.where(held, 0.0, np.einsum("ij,ij->i", V[i], u)),
                  accels=np.where(held, 0.0, np.einsum("ij,ij->i", A[i], u)), t0=float(t0),
                  force_lin=solution.force_lin[row], force_const=solution.force_const[row],
                  origin=np.asarray(solution.origin, dtype=float), mu_static=np.where(loose, 0.0, float(mu_s)),
                  mu_kinetic=np.where(loose, 0.0, float(mu)), keys=tuple(zip(i.tolist(), k.tolist())))


@dataclass(frozen=True)
class Mode:
    """Which wheels stick and which slip: ``state[j]`` is 0 (sticks), +1 or -1 (slips, the sign of its slip speed
    ``J nu - w``; it then pushes with ``-sign mu_k N``) or 2 (free: cannot push)."""

    state: tuple[int, ...]

    @property
    def stick(self) -> np.ndarray:
        """Indices of the sticking wheels."""
        return np.flatnonzero(np.array(self.state, dtype=int) == 0)

    @property
    def slip(self) -> np.ndarray:
        """Indices of the slipping wheels."""
        s = np.array(self.state, dtype=int)
        return np.flatnonzero((s == 1) | (s == -1))

    @property
    def signs(self) -> np.ndarray:
        """(m,) the state as an integer array."""
        return np.array(self.state, dtype=int)


def _masses(mass: float, inertia: float) -> np.ndarray:
    """(3,) generalised masses (kg, kg, kg m^2), refused unless positive (a massless parcel has no dynamics)."""
    if not (mass > 0 and inertia > 0):
        raise ValueError(f"mass (kg) and inertia (kg m^2) must be positive, got {mass}, {inertia}")
    return np.array([mass, mass, inertia], dtype=float)


def _kinematics(wheels: Wheels, t: float, y):
    """Jacobian rows, normal forces (N), slips (m/s), the rows' rate term ``c`` (m/s^2) and wheel accelerations."""
    y = np.asarray(y, dtype=float)
    J = wheels.rows(y[:2])
    N = wheels.normal(y[:2])
    s = J @ y[3:6] - wheels.surface(t)
    u = wheels.directions
    c = -y[5] * (y[3] * u[:, 1] - y[4] * u[:, 0])  # d/dt (r x u) . omega with dr/dt = -v
    return J, N, s, c, wheels.accels


def _stick_solve(J, minv, known, rhs, S):
    """Accelerations and stick forces of sticking set ``S``: ``M nu_dot = known + J_S^T lam_S`` with
    ``J_S nu_dot = rhs_S``; ``lam_S`` minimum-norm (its wrench is unique). Returns (nu_dot, lam_S, F_S)."""
    if len(S) == 0:
        return minv * known, np.zeros(0), np.zeros(3)
    JS = J[S]
    A = (JS * minv) @ JS.T
    lam = np.linalg.lstsq(A, rhs[S] - JS @ (minv * known), rcond=None)[0]
    F = JS.T @ lam
    return minv * (known + F), lam, F


def mode_rhs(wheels: Wheels, mode: Mode, t: float, y, mass: float, inertia: float):
    """The smooth dynamics in ``mode`` at time ``t`` (s), state ``y`` = (x, y, theta, vx, vy, omega).

    Returns ``(y_dot, lam)``: the state's rate and every wheel's force on the parcel (N, along its direction):
    slipping wheels the kinetic ``-sign mu_k N`` (eqs. 20-22 per wheel), sticking wheels the minimum-norm forces
    that keep their slip acceleration zero, free wheels 0.
    """
    mvec = _masses(mass, inertia)
    J, N, s, c, wdot = _kinematics(wheels, t, y)
    sig = mode.signs
    lam = np.zeros(wheels.m)
    L = mode.slip
    lam[L] = -sig[L] * wheels.mu_kinetic[L] * N[L]  # eq. 22 per wheel: mu N along the direction it outruns
    S = mode.stick
    nu_dot, lam_S, _ = _stick_solve(J, 1.0 / mvec, J[L].T @ lam[L], wdot - c, S)
    lam[S] = lam_S
    return np.concatenate([np.asarray(y, dtype=float)[3:6], nu_dot]), lam


def _facet_spec(G) -> tuple:
    """Which generators define the facets of the zonotope with generators the rows of ``G`` (k, 3), within their
    span: ``(rank, anchor, index)``. Rank 3: each facet is spanned by a non-parallel pair ``index[f]``; rank 2 (the
    span is the plane of the pair ``anchor``): each facet is parallel to one generator ``index[f]``; rank 1: the
    facets are the segment's two ends, normal to generator ``index[0]``. Fixed for a mode, so that its event
    functions stay the same while the generators move with the state. Parallel facets (equal unit normals to 1e-8,
    up to sign) are one pair of events: the first of them is kept. Compiled (:func:`_facet_candidates`,
    :func:`_first_distinct`): it runs twice at every event of a run, and in numpy it took ~1-2 ms for 24 wheels."""
    none = np.zeros(0, dtype=np.int64)
    G = np.ascontiguousarray(G, dtype=float)
    if len(G) == 0 or not np.abs(G).max() > 0:
        return 0, None, none
    key = G.tobytes()
    if key in _LAST_FACETS:  # the same generators asked again (deciding a mode checks it, its events then ask)
        return _LAST_FACETS[key]
    _LAST_FACETS.clear()
    _LAST_FACETS[key] = spec = _facets_of(G)
    return spec


_LAST_FACETS: dict[bytes, tuple] = {}
"""The last generators :func:`_facet_spec` was asked about, by their bytes, and its answer (its arrays read-only)."""


def _facets_of(G) -> tuple:
    """:func:`_facet_spec` of generators ``G`` (k, 3) with some non-zero, computed."""
    scale = np.linalg.norm(G, axis=1)
    sv = np.linalg.svd(G / scale.max(), compute_uv=False)
    rank = int((sv > 1e-9 * sv[0]).sum())
    a0, a1, unit, index = _facet_candidates(G, scale, rank)
    if rank == 1:
        index = index[:, 0]
    else:
        index = index[_first_distinct(np.round(unit, 8))]
        index = index[:, 0] if rank == 2 else index
    index.setflags(write=False)
    return rank, ((int(a0), int(a1)) if rank == 2 else None), index


@njit(cache=True)
def _facet_candidates(G, scale, rank):
    """The candidate facets of the zonotope of generators ``G`` (k, 3) of lengths ``scale`` and rank ``rank``:
    (anchor pair, their unit normals (p, 3) with the sign that makes the first component above 1e-6 positive,
    their generators (p, 2): a pair for rank 3, one generator twice for rank 2 (normal to it within the plane of
    the anchor pair, the pair of largest cross product), the longest generator for rank 1)."""
    k = G.shape[0]
    if rank == 1:
        out = np.empty((1, 2), np.int64)
        out[0, 0] = out[0, 1] = np.argmax(scale)
        return 0, 0, np.zeros((0, 3)), out
    pairs = k * (k - 1) // 2
    cross = np.empty((pairs, 3))
    index = np.empty((pairs, 2), np.int64)
    p = 0
    best, a0, a1 = -1.0, 0, 0
    for a in range(k):
        for b in range(a + 1, k):
            cross[p] = _cross3(G[a], G[b])
            index[p, 0], index[p, 1] = a, b
            size = math.sqrt(cross[p, 0] ** 2 + cross[p, 1] ** 2 + cross[p, 2] ** 2)
            if size > best:
                best, a0, a1 = size, a, b
            p += 1
    if rank == 2:
        plane = _cross3(G[a0], G[a1])
        normals = np.empty((k, 3))
        index = np.empty((k, 2), np.int64)
        for a in range(k):
            normals[a] = _cross3(plane, G[a])
            index[a, 0] = index[a, 1] = a
    else:
        normals = cross
    n = normals.shape[0]
    size = np.empty(n)
    for q in range(n):
        size[q] = math.sqrt(normals[q, 0] ** 2 + normals[q, 1] ** 2 + normals[q, 2] ** 2)
    largest = size.max()
    count = 0
    for q in range(n):
        count += size[q] > 1e-9 * largest
    unit = np.empty((count, 3))
    kept = np.empty((count, 2), np.int64)
    c = 0
    for q in range(n):
        if not size[q] > 1e-9 * largest:
            continue
        for e in range(3):
            unit[c, e] = normals[q, e] / size[q]
        lead = unit[c, 0]
        for e in range(3):
            if abs(unit[c, e]) > 1e-6:
                lead = unit[c, e]
                break
        if lead < 0:
            for e in range(3):
                unit[c, e] = -unit[c, e]
        kept[c] = index[q]
        c += 1
    return a0, a1, unit, kept


@njit(cache=True)
def _cross3(a, b):
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit(cache=True)
def _first_distinct(key):
    """Positions of the rows of ``key`` (p, 3) equal to no earlier row, in order."""
    keep = np.empty(key.shape[0], np.int64)
    n = 0
    for q in range(key.shape[0]):
        new = True
        for r in range(n):
            s = keep[r]
            if key[s, 0] == key[q, 0] and key[s, 1] == key[q, 1] and key[s, 2] == key[q, 2]:
                new = False
                break
        if new:
            keep[n] = q
            n += 1
    return keep[:n]


def _facet_normals(G, spec) -> np.ndarray:
    """(f, 3) unit facet normals of the zonotope of generators ``G`` for the facet choice ``spec``."""
    rank, anchor, index = spec
    if rank == 0:
        return np.zeros((0, 3))
    if rank == 1:
        normals = G[index]
    elif rank == 2:
        normals = np.cross(np.cross(G[anchor[0]], G[anchor[1]]), G[index])
    else:
        normals = np.cross(G[index[:, 0]], G[index[:, 1]])
    return normals / np.linalg.norm(normals, axis=1)[:, None]


def _required(wheels: Wheels, mode: Mode, t: float, y, minv):
    """What the mode asks of its sticking wheels at (t, y): their generators ``mu_s N J`` (k, 3) and the net wrench
    ``F_S`` (N, N, N m) they must supply."""
    J, N, s, c, wdot = _kinematics(wheels, t, y)
    L, S = mode.slip, mode.stick
    lam_L = -mode.signs[L] * wheels.mu_kinetic[L] * N[L]
    _, _, F = _stick_solve(J, minv, J[L].T @ lam_L, wdot - c, S)
    return (wheels.mu_static[S] * N[S])[:, None] * J[S], F


def _slack(G, F, spec) -> np.ndarray:
    """Per facet: the zonotope's support along its normal minus the wrench's reach (>= 0: the wrench is inside)."""
    normals = _facet_normals(G, spec)
    return np.abs(G @ normals.T).sum(axis=0) - np.abs(normals @ F)


def mode_events(wheels: Wheels, mode: Mode, t: float, y, mass: float, inertia: float) -> list:
    """Event functions ``g(t, y)`` of ``mode`` entered at time ``t`` (s) and state ``y``, for
    :func:`scipy.integrate.solve_ivp`; each falls through zero at its event (``direction = -1``, terminal).

    Per wheel in contact: its cell's normal force (N; zero where the support set's contact set changes, the
    engine's event, which ends a :func:`simulate`). Per slipping wheel: its slip speed times its sign (m/s; zero
    when it catches up with its wheel). Per facet of the sticking wheels' zonotope (the facets as they are at
    (t, y)): the support of the zonotope along the facet's normal minus that of the required wrench (zero when the
    wrench reaches the facet). Each function carries
    ``kind`` ("support", "slip" or "stick") and ``index`` (the wheel, or the facet).
    """
    minv = 1.0 / _masses(mass, inertia)
    events = []
    for j in np.flatnonzero(wheels.normal(np.asarray(y, dtype=float)[:2]) > 0).tolist():
        def lift(t, y, j=j):
            return float(wheels.force_lin[j] @ (y[:2] - wheels.origin) + wheels.force_const[j])

        lift.kind, lift.index, lift.direction, lift.terminal = "support", j, -1, True
        events.append(lift)
    for j in mode.slip.tolist():
        def slip(t, y, j=j, sign=mode.state[j]):
            return sign * float(wheels.rows(y[:2])[j] @ y[3:6] - wheels.surface(t)[j])

        slip.kind, slip.index, slip.direction, slip.terminal = "slip", j, -1, True
        events.append(slip)
    if len(mode.stick):
        spec = _facet_spec(_required(wheels, mode, t, y, minv)[0])
        last = {}  # the integrator asks every facet at the same (t, y): one KKT solve serves them all

        def slacks(t, y):
            key = (t, y[:6].tobytes())
            if key not in last:
                last.clear()
                last[key] = _slack(*_required(wheels, mode, t, y[:6], minv), spec)
            return last[key]

        for f in range(len(spec[2])):
            def stick(t, y, f=f):
                return float(slacks(t, y)[f])

            stick.kind, stick.index, stick.direction, stick.terminal = "stick", f, -1, True
            stick.spec = spec
            events.append(stick)
    return events


def _box_accelerations(JZ, minv, known, rhs, bounds, max_sweeps=200000, tol=1e-15):
    """Projected Gauss-Seidel on the acceleration-level box problem of the zero-slip wheels: forces ``lam`` within
    ``|lam| <= bounds`` with the slip accelerations ``a = J_Z nu_dot - rhs`` complementary to them. Returns ``a``
    (unique, as ``nu_dot`` is); used to identify the mode, which is then solved and checked exactly. Compiled
    (:func:`box_sweeps`): many redundant wheels (hexagonal omni cells) take thousands of sweeps."""
    JZ = np.ascontiguousarray(JZ, dtype=float)
    diag = ((JZ ** 2) * minv).sum(axis=1)
    z = box_sweeps(JZ, np.ascontiguousarray(minv, dtype=float), np.ascontiguousarray(minv * known, dtype=float),
                   np.ascontiguousarray(rhs, dtype=float), np.ascontiguousarray(bounds, dtype=float), diag,
                   int(max_sweeps), float(tol))
    return JZ @ z - rhs


@njit(cache=True)
def box_sweeps(rows, minv, z0, r, b, diag, max_sweeps, tol):
    """Projected Gauss-Seidel over a box problem: wheel rows ``rows`` (m, 3) ``[u, r x u]``, inverse masses ``minv``
    (3,), targets ``r`` (m,) for ``rows @ z``, bounds ``b`` (m,) on each wheel's |force| (or impulse), ``diag`` (m,)
    the rows' ``J M^-1 J^T`` diagonal; from ``z0`` (3,) with every force at 0, returns the ``z`` (3,) the sweeps
    converge to (a sweep's largest force change at most ``tol`` times the largest bound, or ``max_sweeps``). The mode
    rule's accelerations (:func:`_box_accelerations`, ``z`` in m/s^2) and the law checker's stepped wheels (``z`` the
    twist after a step, m/s, rad/s) both solve with it."""
    z = z0.copy()
    lam = np.zeros(rows.shape[0])
    m0, m1, m2 = minv[0], minv[1], minv[2]
    scale = 1e-300
    for j in range(b.shape[0]):
        scale = max(scale, b[j])
    for _ in range(max_sweeps):
        change = 0.0
        for j in range(rows.shape[0]):
            if b[j] <= 0.0 or diag[j] <= 0.0:
                continue
            p, q, w = rows[j, 0], rows[j, 1], rows[j, 2]
            a = p * z[0] + q * z[1] + w * z[2] - r[j]
            new = min(max(lam[j] - a / diag[j], -b[j]), b[j])
            d = new - lam[j]
            if d:
                lam[j] = new
                z[0] += m0 * p * d
                z[1] += m1 * q * d
                z[2] += m2 * w * d
                change = max(change, abs(d))
        if change <= tol * scale:
            break
    return z


@dataclass(frozen=True)
class ModeEvent:
    """A mode change: at ``time`` (s) the event function ``kind`` ("slip": a slipping wheel reached zero slip;
    "stick": the sticking wheels' required wrench reached a facet of their zonotope) number ``index`` fell to zero,
    and the mode changed from ``before`` to ``after``."""

    time: float
    kind: str
    index: int
    before: Mode
    after: Mode


@njit(cache=True)
def _slip_tol(speed: float, accel: float, t: float) -> float:
    """The slip (m/s) below which a wheel is at zero slip at time ``t`` (s): ``_SLIP_TOL`` of the speed scale
    ``speed`` (m/s), and what the slip can change (``accel`` bounds its rate, m/s^2) within the uncertainty of an
    event's time. The engine's event search (``engine._kernel``) places an event within ``max(4 eps |t|, 1e-13 s)``
    plus ``4 eps |t|`` of its root and steps past it by as much again, so the time is known to ``16 eps |t| + 2e-13``
    s, which grows with the time itself (2.6 ps at 677 s). Without this term a parcel decelerating onto still wheels
    late in a long run found its slip 2e-12 m/s past zero at the event, slipped back the other way, and chattered."""
    return _SLIP_TOL * speed + accel * (_TIME_ULPS * _EPS * abs(t) + _TIME_FLOOR)


def decide_mode(wheels: Wheels, t: float, y, mass: float, inertia: float, *, breaking: dict | None = None) -> Mode:
    """The exact mode at time ``t`` (s) and state ``y`` = (x, y, theta, vx, vy, omega) of a parcel of ``mass`` (kg)
    and ``inertia`` (kg m^2): wheels with non-zero slip keep its sign; wheels at zero slip stick if their static
    bounds can hold them, else slip the way they accelerate (see the module's docstring for the method and the rule
    for redundant sticking wheels). ``breaking`` ({wheel: sign}) names wheels known to leave stick here (the wheels
    at their bounds on a facet the required wrench crosses); they slip with that sign.

    Raises:
        ValueError: the identified mode fails its exact check (a degenerate tie the identification could not split).
    """
    y = np.asarray(y, dtype=float)
    minv = 1.0 / _masses(mass, inertia)
    J, N, s, c, wdot = _kinematics(wheels, t, y)
    rhs = wdot - c
    speed = max(float(np.abs(wheels.surface(t)).max(initial=0.0)), float(np.abs(J @ y[3:]).max(initial=0.0)), 1e-3)
    free = wheels.free | (N <= 0)
    bounds = wheels.mu_static * np.maximum(N, 0.0)
    accel = float(np.abs(rhs).max(initial=0.0) + (np.linalg.norm(J, axis=1) * bounds).sum() * minv.max()) + 1e-300
    state = np.where(free, 2, np.sign(s).astype(int))
    zero = (np.abs(s) <= _slip_tol(speed, accel, t)) & ~free
    state[zero] = 0
    for j, sign in (breaking or {}).items():
        state[j], zero[j] = sign, False
    Z = np.flatnonzero(zero)
    broke = []
    while len(Z):
        L = np.flatnonzero((state == 1) | (state == -1))
        known = J[L].T @ (-state[L] * wheels.mu_kinetic[L] * N[L])
        a = _box_accelerations(J[Z], minv, known, rhs[Z], bounds[Z])
        out = np.abs(a) > _ACCEL_TOL * accel
        if not out.any():
            break
        state[Z[out]] = np.sign(a[out]).astype(int)
        broke.extend(Z[out].tolist())
        Z = Z[~out]
    state[Z] = 0
    mode = Mode(tuple(int(v) for v in state))
    _check(wheels, mode, t, y, minv, broke, accel)
    return mode


def _check(wheels, mode, t, y, minv, broke, accel) -> None:
    """Raise ValueError unless ``mode`` is consistent at (t, y): the required wrench inside the sticking wheels'
    zonotope and every wheel that broke away accelerating in the direction it slips."""
    if len(mode.stick):
        G, F = _required(wheels, mode, t, y, minv)
        spec = _facet_spec(G)
        slack = _slack(G, F, spec)
        scale = float(np.abs(G).sum()) + 1e-300
        if len(slack) and slack.min() < -1e-7 * scale:
            raise ValueError(f"sticking wheels cannot supply the wrench they must at t = {t} s (slack {slack.min():g})")
    if broke:
        J, N, s, c, wdot = _kinematics(wheels, t, y)
        L = mode.slip
        lam = np.zeros(wheels.m)
        lam[L] = -mode.signs[L] * wheels.mu_kinetic[L] * N[L]
        nu_dot, _, _ = _stick_solve(J, minv, J[L].T @ lam[L], wdot - c, mode.stick)
        a = J[broke] @ nu_dot + c[broke] - wdot[broke]
        if (mode.signs[broke] * a < -1e-7 * accel).any():
            raise ValueError(f"a wheel breaking away at t = {t} s would accelerate against its slip")


@dataclass(frozen=True, eq=False)
class StickSlipRun:
    """One parcel's exact stick-slip motion on one support set.

    Attributes:
        segments: per mode, ``(t_start, t_end, mode, solution)`` with ``solution(t)`` the dense state (6 + 2: the
            state, then the wheel work and the dissipation so far).
        events: the :class:`ModeEvent` s, in order.
        wheel_work: J, ``int sum lam w dt`` (the wheels' work on the parcel).
        dissipation: J, ``int -sum lam s dt`` (friction's loss, >= 0).
        kinetic_start, kinetic_end: J.
        t_end: s; y_end: (6,) the final state.
        status: "completed" (reached ``t1``) or "support" (stopped where a wheel's normal force fell to zero: the
            support set's contact set changes there, and the engine must solve the new one and call again).
    """

    segments: list
    events: list
    wheel_work: float
    dissipation: float
    kinetic_start: float
    kinetic_end: float
    t_end: float
    y_end: np.ndarray = field(repr=False)
    status: str = "completed"

    def state(self, t):
        """(6,) state at time ``t`` (s), or (k, 6) for k times."""
        ts = np.atleast_1d(np.asarray(t, dtype=float))
        out = np.empty((len(ts), 6))
        for k, tk in enumerate(ts):
            for t_a, t_b, _, sol in self.segments:
                if tk <= t_b or (t_a, t_b) == self.segments[-1][:2]:
                    out[k] = sol(min(max(tk, t_a), t_b))[:6]
                    break
        return out[0] if np.ndim(t) == 0 else out

    def mode_at(self, t: float) -> Mode:
        """The mode in force at time ``t`` (s) (the later one at an event)."""
        for t_a, t_b, mode, _ in self.segments:
            if t < t_b:
                return mode
        return self.segments[-1][2]


def simulate(wheels: Wheels, y0, t0: float, t1: float, mass: float, inertia: float, *, rtol: float = 1e-10,
             atol: float = 1e-13, max_events: int = 10000) -> StickSlipRun:
    """Integrate one parcel of ``mass`` (kg) and ``inertia`` (kg m^2) from state ``y0`` at ``t0`` to ``t1`` (s) on
    the fixed support set of ``wheels``: each mode with :func:`scipy.integrate.solve_ivp` (DOP853, dense output) and
    its :func:`mode_events`, the mode decided again by :func:`decide_mode` at every event. At an event the twist is
    projected onto the new sticking wheels' constraints (a correction of the size of the root's error) so that a
    parcel riding its wheels does so to round-off. The wheel work and the dissipation are integrated alongside. The
    run stops early (``status`` "support", last event of kind "support") where a wheel's normal force falls to zero:
    beyond it this support set's normal-force map no longer holds.

    Raises:
        ValueError: more than ``max_events`` events (chattering), or the integrator failed.
    """
    minv = 1.0 / _masses(mass, inertia)
    mvec = 1.0 / minv
    y = np.array(y0, dtype=float)
    if y.shape != (6,) or not np.isfinite(y).all():
        raise ValueError("y0 must be a finite state (x, y, theta, vx, vy, omega)")
    mode = decide_mode(wheels, t0, y, mass, inertia)
    y = _project(wheels, mode, t0, y, minv)
    z = np.concatenate([y, [0.0, 0.0]])
    kinetic_start = 0.5 * float(mvec @ y[3:] ** 2)
    segments, events, t = [], [], float(t0)

    while True:
        def rates(t, z, mode=mode):
            ydot, lam = mode_rhs(wheels, mode, t, z[:6], mass, inertia)
            slip = wheels.slips(t, z[:6])
            return np.concatenate([ydot, [float(lam @ wheels.surface(t)), -float(lam @ slip)]])

        fns = mode_events(wheels, mode, t, z[:6], mass, inertia)
        sol = solve_ivp(rates, (t, t1), z, method="DOP853", rtol=rtol, atol=atol, events=fns or None,
                        dense_output=True)
        if sol.status < 0:
            raise ValueError(f"integration failed at t = {sol.t[-1]} s: {sol.message}")
        segments.append((t, float(sol.t[-1]), mode, sol.sol))
        t, z = float(sol.t[-1]), sol.y[:, -1].copy()
        if sol.status == 0:
            status = "completed"
            break
        hit = min((float(te[0]), k) for k, te in enumerate(sol.t_events) if len(te))[1]
        fn = fns[hit]
        if fn.kind == "support":
            events.append(ModeEvent(t, fn.kind, int(fn.index), mode, mode))
            status = "support"
            break
        breaking = _breaking(wheels, mode, t, z[:6], minv, fn.spec, fn.index) if fn.kind == "stick" else None
        new = decide_mode(wheels, t, z[:6], mass, inertia, breaking=breaking)
        z[:6] = _project(wheels, new, t, z[:6], minv)
        events.append(ModeEvent(t, fn.kind, int(fn.index), mode, new))
        if len(events) > max_events:
            raise ValueError(f"more than {max_events} mode changes by t = {t} s (chattering)")
        mode = new
    y = z[:6]
    return StickSlipRun(segments, events, float(z[6]), float(z[7]), kinetic_start, 0.5 * float(mvec @ y[3:] ** 2),
                        t, y, status)


def _breaking(wheels, mode, t, y, minv, spec, facet) -> dict:
    """The wheels that leave stick where the required wrench crosses facet ``facet`` of ``spec``: those off the
    facet's plane, each at its static bound ``lam_j`` there, slipping against it (sign ``-sign(lam_j)``)."""
    G, F = _required(wheels, mode, t, y, minv)
    rank, anchor, index = spec
    n = _facet_normals(G, (rank, anchor, index[facet:facet + 1]))[0]
    reach = G @ n
    off = np.abs(reach) > _PLANE_TOL * np.linalg.norm(G, axis=1)
    side = np.sign(n @ F) or 1.0
    S = mode.stick
    return {int(S[k]): int(-side * np.sign(reach[k])) for k in np.flatnonzero(off)}


def _project(wheels, mode, t, y, minv) -> np.ndarray:
    """``y`` with its twist moved (the least change in the kinetic metric) onto the sticking wheels' constraints
    ``J_S nu = w_S``."""
    S = mode.stick
    if not len(S):
        return y
    JS = wheels.rows(y[:2])[S]
    gap = JS @ y[3:] - wheels.surface(t)[S]
    out = y.copy()
    out[3:] -= minv * (JS.T @ np.linalg.lstsq((JS * minv) @ JS.T, gap, rcond=None)[0])
    return out


def stick_facets(wheels: Wheels, mode: Mode, t: float, y, mass: float, inertia: float) -> tuple:
    """The facet choice ``(rank, anchor, index)`` of the sticking wheels' zonotope of ``mode`` at (t, y), indices
    into ``mode.stick`` (see :func:`mode_events`: fixed for the mode, as the facets keep their generators while
    the state moves). For an engine that evaluates the facets' slacks itself."""
    return _facet_spec(_required(wheels, mode, t, y, 1.0 / _masses(mass, inertia))[0])


def breaking_wheels(wheels: Wheels, mode: Mode, t: float, y, mass: float, inertia: float, spec: tuple,
                    facet: int) -> dict:
    """``{wheel: sign}`` of the wheels that leave stick where the required wrench of ``mode`` crosses facet
    ``facet`` of the facet choice ``spec`` (:func:`stick_facets`) at (t, y): :func:`decide_mode`'s ``breaking``."""
    return _breaking(wheels, mode, t, np.asarray(y, dtype=float), 1.0 / _masses(mass, inertia), spec, facet)


def project_twist(wheels: Wheels, mode: Mode, t: float, y, mass: float, inertia: float) -> np.ndarray:
    """``y`` (x, y, theta, vx, vy, omega) with its twist moved, the least in the kinetic metric, onto the sticking
    wheels' constraints of ``mode`` at time ``t`` (s): what :func:`simulate` does at every mode change."""
    return _project(wheels, mode, t, np.asarray(y, dtype=float), 1.0 / _masses(mass, inertia))


# --- The mode decision compiled ------------------------------------------------------------------------------------
# The functions above are the readable reference; those below do the same in one compiled call (the engine decides a
# mode at every event and support change, where the reference's Python took ~1.5 ms). They take a wheel set as the
# ten arrays of :func:`wheel_arrays` (``Wheels``' fields, in its order), so that the engine builds no objects.


def wheel_arrays(cells, support, solution, velocities, mu: float, mu_static: float | None = None) -> tuple:
    """:func:`wheels_on`'s wheel set (no stuck or free wheels, no accelerations, ``t0`` 0) as the tuple
    ``(points, directions, speeds, accels, t0, force_lin, force_const, origin, mu_static, mu_kinetic)`` (SI units as
    :class:`Wheels`), built in compiled code and unchecked: what the engine passes to :func:`decide_kernel`."""
    mu_s = mu if mu_static is None else mu_static
    return _wheel_arrays(cells.wheel_active, cells.drive_directions, cells.positions,
                         np.ascontiguousarray(velocities, dtype=float), np.asarray(support, dtype=np.int64),
                         np.ascontiguousarray(solution.force_lin, dtype=float),
                         np.ascontiguousarray(solution.force_const, dtype=float),
                         np.ascontiguousarray(solution.origin, dtype=float), float(mu), float(mu_s))


def arrays_of(wheels: Wheels) -> tuple:
    """The ten arrays of :func:`wheel_arrays` of a :class:`Wheels`."""
    return (np.ascontiguousarray(wheels.points), np.ascontiguousarray(wheels.directions),
            np.ascontiguousarray(wheels.speeds), np.ascontiguousarray(wheels.accels), float(wheels.t0),
            np.ascontiguousarray(wheels.force_lin), np.ascontiguousarray(wheels.force_const),
            np.ascontiguousarray(wheels.origin), np.ascontiguousarray(wheels.mu_static),
            np.ascontiguousarray(wheels.mu_kinetic))


@njit(cache=True)
def _wheel_arrays(active, directions, positions, V, support, force_lin, force_const, origin, mu, mu_s):
    """The wheels of entries ``support``, each present wheel in entry order (as ``np.nonzero`` of ``active``)."""
    m = 0
    for r in range(support.shape[0]):
        for k in range(2):
            m += active[support[r], k]
    P, U = np.empty((m, 2)), np.empty((m, 2))
    w, FL, FC = np.empty(m), np.empty((m, 2)), np.empty(m)
    j = 0
    for r in range(support.shape[0]):
        i = support[r]
        for k in range(2):
            if not active[i, k]:
                continue
            P[j, 0], P[j, 1] = positions[i, 0], positions[i, 1]
            U[j, 0], U[j, 1] = directions[i, k, 0], directions[i, k, 1]
            w[j] = V[i, 0] * U[j, 0] + V[i, 1] * U[j, 1]
            FL[j, 0], FL[j, 1], FC[j] = force_lin[r, 0], force_lin[r, 1], force_const[r]
            j += 1
    return P, U, w, np.zeros(m), 0.0, FL, FC, origin.copy(), np.full(m, mu_s), np.full(m, mu)


@njit(cache=True)
def _kinematics_c(P, U, w0, wa, t0, FL, FC, origin, t, y):
    """:func:`_kinematics` compiled: rows J (m, 3), normal forces N, slips s, rate terms c, surface speeds w."""
    m = P.shape[0]
    J, N, s, c, w = np.empty((m, 3)), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    for j in range(m):
        ux, uy = U[j, 0], U[j, 1]
        J[j, 0], J[j, 1], J[j, 2] = ux, uy, (P[j, 0] - y[0]) * uy - (P[j, 1] - y[1]) * ux
        N[j] = FL[j, 0] * (y[0] - origin[0]) + FL[j, 1] * (y[1] - origin[1]) + FC[j]
        w[j] = w0[j] + wa[j] * (t - t0)
        s[j] = J[j, 0] * y[3] + J[j, 1] * y[4] + J[j, 2] * y[5] - w[j]
        c[j] = -y[5] * (y[3] * uy - y[4] * ux)  # d/dt (r x u) . omega with dr/dt = -v
    return J, N, s, c, w


@njit(cache=True)
def _known_c(J, N, muk, state):
    """The slipping wheels' kinetic wrench (eq. 22 per wheel: ``-sign mu_k N`` along each direction)."""
    known = np.zeros(3)
    for j in range(state.shape[0]):
        if state[j] == 1 or state[j] == -1:
            lam = -state[j] * muk[j] * N[j]
            for e in range(3):
                known[e] += J[j, e] * lam
    return known


@njit(cache=True)
def _lstsq_wrench(JS, minv, gap):
    """``J_S^T lam`` for the minimum-norm least-squares ``lam`` of ``(J_S M^-1 J_S^T) lam = gap``, as
    :func:`_stick_solve` and :func:`_project` (numpy's ``lstsq``) give it, without a k x k factorisation: with
    ``B = J_S M^-1/2`` the wrench is ``M^1/2 B^+ gap``, and ``B^+ gap`` lies in the span of the independent rows
    ``J_R`` (:func:`_independent_c`), so it is ``J_R^T alpha`` with ``alpha`` the least-squares solution of
    ``(J_S M^-1 J_R^T) alpha = gap`` (k x r, r <= 3, full column rank: a Gram-Schmidt QR, twice for rounding)."""
    k = JS.shape[0]
    R = _independent_c(JS, np.arange(k))
    r = R.shape[0]
    F = np.zeros(3)
    if r == 0:
        return F
    C = np.empty((k, r))
    for a in range(k):
        for b in range(r):
            q = R[b]
            C[a, b] = JS[a, 0] * minv[0] * JS[q, 0] + JS[a, 1] * minv[1] * JS[q, 1] + JS[a, 2] * minv[2] * JS[q, 2]
    Q = C.copy()
    T = np.zeros((r, r))
    for b in range(r):
        for _ in range(2):
            for e in range(b):
                d = 0.0
                for a in range(k):
                    d += Q[a, e] * Q[a, b]
                T[e, b] += d
                for a in range(k):
                    Q[a, b] -= d * Q[a, e]
        size = 0.0
        for a in range(k):
            size += Q[a, b] ** 2
        size = math.sqrt(size)
        T[b, b] = size
        for a in range(k):
            Q[a, b] /= size
    alpha = np.empty(r)
    for b in range(r - 1, -1, -1):
        acc = 0.0
        for a in range(k):
            acc += Q[a, b] * gap[a]
        for e in range(b + 1, r):
            acc -= T[b, e] * alpha[e]
        alpha[b] = acc / T[b, b]
    for b in range(r):
        for e in range(3):
            F[e] += JS[R[b], e] * alpha[b]
    return F


@njit(cache=True)
def _required_c(J, N, c, wa, mus, muk, state, S, minv):
    """:func:`_required` compiled: the generators ``mu_s N J`` (k, 3) of sticking wheels ``S``, the net wrench
    ``F_S`` they must supply and the slipping wheels' wrench."""
    known = _known_c(J, N, muk, state)
    k = S.shape[0]
    JS, G, gap = np.empty((k, 3)), np.empty((k, 3)), np.empty(k)
    for a in range(k):
        j = S[a]
        acc = 0.0
        for e in range(3):
            JS[a, e] = J[j, e]
            G[a, e] = mus[j] * N[j] * J[j, e]
            acc += J[j, e] * minv[e] * known[e]
        gap[a] = (wa[j] - c[j]) - acc
    return G, (_lstsq_wrench(JS, minv, gap) if k else np.zeros(3)), known


@njit(cache=True)
def _facets_c(G):
    """:func:`_facet_spec` compiled: (rank, anchor (2,), index (f, 2); rank 1 and 2 repeat their one generator)."""
    k = G.shape[0]
    anchor = np.zeros(2, np.int64)
    largest = 0.0
    for a in range(k):
        for e in range(3):
            largest = max(largest, abs(G[a, e]))
    if k == 0 or not largest > 0:
        return 0, anchor, np.zeros((0, 2), np.int64)
    scale = np.empty(k)
    for a in range(k):
        scale[a] = math.sqrt(G[a, 0] ** 2 + G[a, 1] ** 2 + G[a, 2] ** 2)
    sv = np.linalg.svd(G / scale.max(), full_matrices=False)[1]
    rank = 0
    for v in sv:
        rank += v > 1e-9 * sv[0]
    a0, a1, unit, index = _facet_candidates(G, scale, rank)
    if rank == 1:
        return 1, anchor, index
    keep = _first_distinct(np.rint(unit * 1e8) / 1e8)  # np.round(unit, 8), as the reference
    anchor[0], anchor[1] = a0, a1
    out = np.empty((keep.shape[0], 2), np.int64)
    for f in range(keep.shape[0]):
        out[f, 0], out[f, 1] = index[keep[f], 0], index[keep[f], 1]
    return rank, anchor, out


@njit(cache=True)
def _normal_c(G, rank, anchor, p, q):
    """The unit normal of the facet of generators ``p``, ``q`` (:func:`_facet_normals`)."""
    if rank == 1:
        n = G[p].copy()
    elif rank == 2:
        n = _cross3(_cross3(G[anchor[0]], G[anchor[1]]), G[p])
    else:
        n = _cross3(G[p], G[q])
    return n / math.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)


@njit(cache=True)
def _min_slack_c(G, F, rank, anchor, index):
    """The least of :func:`_slack` over the facets (inf without facets)."""
    least = np.inf
    for f in range(index.shape[0]):
        n = _normal_c(G, rank, anchor, index[f, 0], index[f, 1])
        support = 0.0
        for a in range(G.shape[0]):
            support += abs(G[a, 0] * n[0] + G[a, 1] * n[1] + G[a, 2] * n[2])
        least = min(least, support - abs(n[0] * F[0] + n[1] * F[1] + n[2] * F[2]))
    return least


@njit(cache=True)
def zonotope_inradius(G):
    """The radius of the largest ball about the origin inside the zonotope ``{G^T mu : |mu_j| <= 1}`` of the
    generators ``G`` (k, 3) (the rows ``mu_s N J`` of sticking wheels: N, N, N m): the least of its support function
    ``h(n) = sum_j |G_j . n|`` over unit directions, which a polytope takes at a facet normal; every facet normal is
    the cross product of two non-parallel generators, and every other direction's ``h`` is no smaller, so the least
    over those products is exact (O(k^3), no facet bookkeeping). 0 below rank 3 (the products then include the
    normal of the plane the generators span). A wrench of length at most this lies in the zonotope whatever its
    direction: the sticking wheels can hold it (the rule above)."""
    k = G.shape[0]
    least = np.inf
    for p in range(k):
        lp = math.sqrt(G[p, 0] ** 2 + G[p, 1] ** 2 + G[p, 2] ** 2)
        for q in range(p + 1, k):
            n = _cross3(G[p], G[q])
            size = math.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
            lq = math.sqrt(G[q, 0] ** 2 + G[q, 1] ** 2 + G[q, 2] ** 2)
            if not size > _PLANE_TOL * lp * lq:
                continue  # parallel: no facet between them
            h = 0.0
            for a in range(k):
                h += abs(G[a, 0] * n[0] + G[a, 1] * n[1] + G[a, 2] * n[2])
            least = min(least, h / size)
    return least if least < np.inf else 0.0


@njit(cache=True)
def zonotope_grip(G, d, rounding):
    """How much of a pure force (no torque about the centre of mass) the zonotope ``Z = {G^T mu : |mu_j| <= 1}`` of
    the generators ``G`` (k, 3) holds (the rows ``mu_s N J`` of sticking wheels, rank 3: N, N, N m), facet by facet.

    With each facet's unit normal ``n`` and support ``h(n) = sum_j |G_j . n| - rounding`` (N), a wrench ``W`` lies in
    ``Z`` iff ``|n . W| <= h(n)`` at every facet. For the force ``F`` (N) taken about a point ``Delta`` (m) from the
    centre, ``W = (F, Delta x F)``, so ``W`` is in ``c Z`` if ``|F| (g + |Delta| b) <= c`` with ``g`` the largest
    ``|n_xy . d| / h`` (``d`` the unit direction of ``F``) and ``b`` the largest ``|n_z| / h`` over the facets; and a
    direction ``d'`` gives ``g(d') <= g(d) + a |d' - d|`` with ``a`` the largest ``|n_xy| / h``. Returns
    ``(g, a, b)`` (1/N, 1/N, 1/(N m)); ``(inf, inf, inf)`` when a facet has no support beyond ``rounding``.

    Every facet normal of a rank-3 zonotope is the cross product of two non-parallel generators, and every such
    product's plane bounds ``Z``, so taking them all is exact (O(k^3)). Unlike :func:`zonotope_inradius` this weighs
    the torque facets (N m) by the torque a pure force has, which is none about the centre: on 0.1 m cells the
    inradius is set by them, about a tenth of ``mu_s`` times the weight, while a pure force finds the force facets."""
    k = G.shape[0]
    g = a = b = 0.0
    for p in range(k):
        lp = math.sqrt(G[p, 0] ** 2 + G[p, 1] ** 2 + G[p, 2] ** 2)
        for q in range(p + 1, k):
            n = _cross3(G[p], G[q])
            size = math.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
            lq = math.sqrt(G[q, 0] ** 2 + G[q, 1] ** 2 + G[q, 2] ** 2)
            if not size > _PLANE_TOL * lp * lq:
                continue  # parallel: no facet between them
            n0, n1, n2 = n[0] / size, n[1] / size, n[2] / size
            h = -rounding
            for c in range(k):
                h += abs(G[c, 0] * n0 + G[c, 1] * n1 + G[c, 2] * n2)
            if not h > 0:
                return np.inf, np.inf, np.inf
            g = max(g, abs(n0 * d[0] + n1 * d[1]) / h)
            a = max(a, math.sqrt(n0 * n0 + n1 * n1) / h)
            b = max(b, abs(n2) / h)
    return g, a, b


@njit(cache=True)
def _independent_c(J, S):
    """Positions in ``S`` of a maximal independent subset of its rows (at most three), chosen in order by
    Gram-Schmidt (twice, for rounding), a row kept when its part off the others exceeds 1e-9 of its length."""
    basis = np.empty((3, 3))
    chosen = np.empty(3, np.int64)
    r = 0
    for a in range(S.shape[0]):
        row = J[S[a]]
        rest = row.copy()
        for _ in range(2):
            for b in range(r):
                d = rest[0] * basis[b, 0] + rest[1] * basis[b, 1] + rest[2] * basis[b, 2]
                for e in range(3):
                    rest[e] -= d * basis[b, e]
        size = math.sqrt(rest[0] ** 2 + rest[1] ** 2 + rest[2] ** 2)
        if size > 1e-9 * math.sqrt(row[0] ** 2 + row[1] ** 2 + row[2] ** 2):
            basis[r] = rest / size
            chosen[r] = a
            r += 1
            if r == 3:
                break
    return chosen[:r].copy()


@njit(cache=True)
def _all_stick_c(J, N, c, wa, mus, muk, state, Z, minv, rhs, accel):
    """True where every zero-slip wheel ``Z`` clearly sticks: their constraints are consistent (the exact solve
    leaves no slip acceleration, to a thousandth of the identification's threshold) and the wrench they must supply
    lies inside their zonotope by more than rounding. Then the box problem's unique acceleration keeps all of them at
    zero slip, which its sweeps would find (slowly where many wheels are redundant: ~0.1-0.6 ms for 24). Returns
    that and what the exact check needs then: the generators, the required wrench, the slipping wheels' wrench and
    the facet choice."""
    G, F, known = _required_c(J, N, c, wa, mus, muk, state, Z, minv)
    rank, anchor, index = 0, np.zeros(2, np.int64), np.zeros((0, 2), np.int64)
    for a in range(Z.shape[0]):
        j = Z[a]
        acc = -rhs[j]
        for e in range(3):
            acc += J[j, e] * minv[e] * (known[e] + F[e])
        if abs(acc) > 1e-3 * _ACCEL_TOL * accel:
            return False, G, F, known, rank, anchor, index
    rank, anchor, index = _facets_c(G)
    inside = _min_slack_c(G, F, rank, anchor, index) > 1e-9 * (np.abs(G).sum() + 1e-300)
    return inside, G, F, known, rank, anchor, index


@njit(cache=True)
def decide_kernel(P, U, w0, wa, t0, FL, FC, origin, mus, muk, minv, t, y, breaking, signs):
    """:func:`decide_mode` and :func:`project_twist` in one compiled call, for the wheel set of :func:`wheel_arrays`
    at time ``t`` (s), state ``y`` (6,), inverse masses ``minv`` (1/kg, 1/kg, 1/(kg m^2)); ``breaking`` (b,) wheels
    known to leave stick with slip signs ``signs`` (b,). The same two stages as the reference: projected
    Gauss-Seidel identifies the wheels that keep zero slip acceleration (skipped where all of them clearly stick,
    :func:`_all_stick_c`), then the mode is solved and checked exactly (the required wrench inside the sticking
    wheels' zonotope by its facets, every breaking wheel accelerating the way it slips).

    Returns (ok, state (m,) as :attr:`Mode.state`, ``y`` with its twist projected onto the sticking constraints,
    the sticking wheels' independent rows (positions in the sticking wheels, :func:`_independent_c`), the sticking
    wheels, and their zonotope's facet choice: rank, anchor (2,), index (f, 2)). ``ok`` False where the reference
    raises (the mode fails its check); the rest is then meaningless."""
    m = P.shape[0]
    J, N, s, c, w = _kinematics_c(P, U, w0, wa, t0, FL, FC, origin, t, y)
    rhs = wa - c
    speed = 1e-3
    for j in range(m):
        speed = max(speed, abs(w[j]), abs(J[j, 0] * y[3] + J[j, 1] * y[4] + J[j, 2] * y[5]))
    bounds = np.empty(m)
    reach = 0.0
    top = 0.0
    for j in range(m):
        bounds[j] = mus[j] * max(N[j], 0.0)
        reach += math.sqrt(J[j, 0] ** 2 + J[j, 1] ** 2 + J[j, 2] ** 2) * bounds[j]
        top = max(top, abs(rhs[j]))
    accel = top + reach * minv.max() + 1e-300
    tol = _slip_tol(speed, accel, t)
    state = np.empty(m, np.int64)
    zero = np.zeros(m, np.bool_)
    for j in range(m):
        if mus[j] == 0 or N[j] <= 0:
            state[j] = 2
        elif abs(s[j]) <= tol:
            state[j], zero[j] = 0, True
        else:
            state[j] = 1 if s[j] > 0 else -1
    for b in range(breaking.shape[0]):
        state[breaking[b]], zero[breaking[b]] = signs[b], False
    broke = np.zeros(m, np.bool_)
    Z = np.flatnonzero(zero)
    fast = False
    while Z.shape[0]:
        fast, G, F, known, rank, anchor, index = _all_stick_c(J, N, c, wa, mus, muk, state, Z, minv, rhs, accel)
        if fast:
            break  # the identification's answer known without its sweeps
        known = _known_c(J, N, muk, state)
        JZ = np.ascontiguousarray(J[Z])
        diag = np.empty(Z.shape[0])
        for a in range(Z.shape[0]):
            diag[a] = JZ[a, 0] ** 2 * minv[0] + JZ[a, 1] ** 2 * minv[1] + JZ[a, 2] ** 2 * minv[2]
        z = box_sweeps(JZ, minv, minv * known, rhs[Z], bounds[Z], diag, 200000, 1e-15)
        keep = np.ones(Z.shape[0], np.bool_)
        for a in range(Z.shape[0]):
            acc = JZ[a, 0] * z[0] + JZ[a, 1] * z[1] + JZ[a, 2] * z[2] - rhs[Z[a]]
            if abs(acc) > _ACCEL_TOL * accel:
                state[Z[a]] = 1 if acc > 0 else -1
                broke[Z[a]] = True
                keep[a] = False
        if keep.all():
            break
        Z = Z[keep]
    S = np.flatnonzero(state == 0)
    ok = True
    if not fast:  # (else the sticking wheels are Z, checked inside their zonotope already)
        rank, anchor, index = 0, np.zeros(2, np.int64), np.zeros((0, 2), np.int64)
        G, F, known = _required_c(J, N, c, wa, mus, muk, state, S, minv)
        if S.shape[0]:
            rank, anchor, index = _facets_c(G)
            if _min_slack_c(G, F, rank, anchor, index) < -1e-7 * (np.abs(G).sum() + 1e-300):
                ok = False
    for j in range(m):
        if broke[j]:
            acc = c[j] - wa[j]
            for e in range(3):
                acc += J[j, e] * minv[e] * (known[e] + F[e])
            if state[j] * acc < -1e-7 * accel:
                ok = False
    out = y.copy()
    if S.shape[0]:
        JS, gap = np.empty((S.shape[0], 3)), np.empty(S.shape[0])
        for a in range(S.shape[0]):
            JS[a] = J[S[a]]
            gap[a] = s[S[a]]
        F = _lstsq_wrench(JS, minv, gap)
        for e in range(3):
            out[3 + e] -= minv[e] * F[e]
    return ok, state, out, _independent_c(J, S), S, rank, anchor, index


@njit(cache=True)
def breaking_kernel(P, U, w0, wa, t0, FL, FC, origin, mus, muk, minv, t, y, state, S, rank, anchor, index, facet):
    """:func:`breaking_wheels` compiled, for a mode given as :func:`decide_kernel` returns it: the wheels (b,) that
    leave stick where the required wrench crosses facet ``facet`` and their slip signs (b,)."""
    J, N, s, c, w = _kinematics_c(P, U, w0, wa, t0, FL, FC, origin, t, y)
    G, F, _ = _required_c(J, N, c, wa, mus, muk, state, S, minv)
    n = _normal_c(G, rank, anchor, index[facet, 0], index[facet, 1])
    along = n[0] * F[0] + n[1] * F[1] + n[2] * F[2]
    side = 1.0 if along >= 0 else -1.0  # np.sign(0) or 1.0
    wheels, signs = np.empty(S.shape[0], np.int64), np.empty(S.shape[0], np.int64)
    b = 0
    for a in range(S.shape[0]):
        r = G[a, 0] * n[0] + G[a, 1] * n[1] + G[a, 2] * n[2]
        if abs(r) > _PLANE_TOL * math.sqrt(G[a, 0] ** 2 + G[a, 1] ** 2 + G[a, 2] ** 2):
            wheels[b], signs[b] = S[a], int(-side * (1.0 if r > 0 else -1.0))
            b += 1
    return wheels[:b].copy(), signs[:b].copy()


def decide_compiled(wheels: Wheels, t: float, y, mass: float, inertia: float, *,
                    breaking: dict | None = None) -> tuple:
    """:func:`decide_mode`, :func:`project_twist` and :func:`stick_facets` in one compiled call
    (:func:`decide_kernel`): returns (mode, ``y`` (6,) with its twist projected onto the mode's sticking wheels,
    the facet choice (rank, anchor or None, index (f, 2) into ``mode.stick``; rank 1 and 2 repeat the generator)).

    Raises:
        ValueError: where :func:`decide_mode` does (the identified mode fails its exact check).
    """
    minv = 1.0 / _masses(mass, inertia)
    items = list((breaking or {}).items())
    ok, state, out, _, _, rank, anchor, index = decide_kernel(
        *arrays_of(wheels), minv, float(t), np.array(y, dtype=float), np.array([j for j, _ in items], np.int64),
        np.array([s for _, s in items], np.int64))
    if not ok:
        raise ValueError(f"the mode identified at t = {t} s fails its exact check")
    return Mode(tuple(state.tolist())), out, (rank, (int(anchor[0]), int(anchor[1])) if rank == 2 else None, index)
