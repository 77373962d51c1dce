"""Stick-slip parcels translating over one uniform wheel field, events and all, in closed form.

Units: SI (m, s, kg, N, J, rad).

Under the stick-slip law (:mod:`virtual_vehicle.physics.stick_modes`) take a square lattice whose every cell has its
two wheels, along the same two orthogonal directions ``e1`` and ``e2`` in every cell, and a parcel that does not
turn, whose cells under it all move at one surface velocity ``u`` over the window (those around it may do anything:
they push nothing). Each wheel carries its cell's whole normal force
(eq. 21) and the normal forces balance the weight and its moments about the centre of mass (eqs. 3-5, 19), so
``sum N_i = W`` and ``sum N_i r_i = 0``. With ``s_k = (v - u) . e_k`` the slip along axis ``k``:

- the axis' wheels that slip all slip the same way and push with ``-sign(s_k) mu_k N_i`` each (eqs. 20-22 per
  wheel): a force ``-sign(s_k) mu_k W`` along ``e_k`` and, by the moment balance, no torque. The parcel translates
  at ``-sign(s_k) mu_k g`` along that axis, whatever cells carry it, until the slip reaches zero;
- the axis' wheels that stick must supply the wrench that keeps the other axis' motion a translation: zero, which
  lies in every zonotope of static bounds (the rule of :mod:`~virtual_vehicle.physics.stick_modes`), so they
  stick for good (with any ``mu_s > 0``). A slipping axis that catches up is a mode event (its wheels go from
  slipping to sticking), and then rides.

So the motion is one closed form per axis (a parabola until the axis catches up, a line after), both axes
independent, and the only other events are support events: a cell centre crossing one of the footprint's edges,
each edge's margin a quadratic in time per phase, solved in closed form. The support set between them has the
rigid-plate normal forces of eq. 7 (the 3 x 3 moment system of :mod:`virtual_vehicle.physics.contact`, every cell
in contact); a piece where one of them would come within a billionth of the weight of zero (a lift-off), a support
set on one line, a parcel that turns, a slip too close to zero to say whether the engine's rule calls it zero, and
events too close together to say how the engine would group them are all handed back to the event-driven engine
(:mod:`virtual_vehicle.engine.dynamics`), whose results these are, to rounding: the same events and pieces, the
same modes, the energy account in closed form (the wheels' work ``-sign(s_k) mu_k W u_k`` per second of slip, the
dissipation ``mu_k W |s_k|`` integrated). :class:`GlideStepper` writes the window of every such parcel (in one
compiled call each) where the plant would have run the event loop.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from virtual_vehicle.engine.stepping import Event, Trajectory
from virtual_vehicle.model.parcel import ALL_PRESENT, _within

MERGE = 1e-12
"""Event times (s, relative to ``max(1, t)``) this close are one event: the same crossing computed twice."""
APART = 1e-9
"""Event times (s) closer than this but not the same are handed back: how the engine groups them is not known."""
LIFT = 1e-9
"""A normal force below this share of the weight hands the piece back (a lift-off, eq. 19 with springs that cannot
pull, is the engine's to find)."""

_OK, _TURNS, _UNSURE_SLIP, _NOT_UNIFORM, _NO_GRIP, _NO_SUPPORT, _CLOSE, _LINE, _LIFTS, _WIDE = range(10)
REASONS = ("glides", "turns", "a slip too close to zero to call", "cells under it moving otherwise", "no friction",
           "no cell under it", "events too close together", "support on one line", "a cell lifting off",
           "more events than the arrays hold")
"""Why :func:`glide_window` hands a window back, by its code."""


@njit(cache=True)
def _axis(v0, a, tk, u, tau):
    """Position (m) and speed (m/s) along one axis at ``tau`` (s) into the window: ``v0 tau + a tau^2 / 2`` until
    the axis catches up at ``tk`` (negative: it rides from the start, ``a`` 0), then at the wheels' speed ``u``."""
    if tk < 0.0 or tau <= tk:
        return v0 * tau + 0.5 * a * tau * tau, v0 + a * tau
    return v0 * tk + 0.5 * a * tk * tk + u * (tau - tk), u


@njit(cache=True)
def _phase(v0, a, tk, u, tau):
    """The axis' position over the phase holding ``tau`` as ``alpha + beta tau + gamma tau^2`` (m)."""
    if tk < 0.0 or tau <= tk:
        return 0.0, v0, 0.5 * a
    return v0 * tk + 0.5 * a * tk * tk - u * tk, u, 0.0


@njit(cache=True)
def _inside(px, py, wn, offsets):
    """Whether the point (px, py) (m, from the footprint's centre) lies strictly inside its half-planes (world
    normals ``wn``, ``offsets`` m): every edge margin positive, as the engine counts a cell under a parcel."""
    for q in range(offsets.shape[0]):
        if offsets[q] - (wn[q, 0] * px + wn[q, 1] * py) <= 0.0:
            return False
    return True


@njit(cache=True)
def _roots(A, B, C, lo, hi, out, n):
    """Append to ``out`` (from ``n``) the roots of ``A + B tau + C tau^2`` in ``(lo, hi]``; returns the new count."""
    scale = abs(A) + abs(B) * hi + abs(C) * hi * hi + 1e-300
    if abs(C) * hi * hi <= 1e-14 * scale:
        if abs(B) * hi > 1e-14 * scale:
            r = -A / B
            if lo < r <= hi:
                out[n] = r
                n += 1
        return n
    disc = B * B - 4.0 * A * C
    if disc < 0.0:
        return n
    q = -0.5 * (B + math.copysign(math.sqrt(disc), B))  # the stable pair of roots
    r1 = q / C
    r2 = A / q if q != 0.0 else r1
    for r in (r1, r2):
        if lo < r <= hi:
            out[n] = r
            n += 1
    return n


@njit(cache=True)
def glide_window(points, order, start, lo0, lo1, size, nx, ny, present, positions, V, e1, e2, y, t0, T, taus,
                 normals, offsets, radius, mu, mu_s, gravity, mass, inertia):
    """One parcel's window of ``T`` s from time ``t0`` (s) and state ``y`` (x, y, theta m m rad, vx, vy m/s, omega
    rad/s), as the module docstring solves it, on the contact layer's ``positions`` (n, 2) moving at ``V`` (n, 2)
    m/s, every cell with wheels along ``e1`` and ``e2`` (the grid's arrays as :func:`_within` takes them; ``present``
    empty for every cell). ``taus`` are the sample times less ``t0``; the footprint is its body-frame half-planes
    ``normals`` (k, 2), ``offsets`` (k,) m and its ``radius`` (m); ``mu``, ``mu_s`` the kinetic and static
    coefficients, ``gravity`` m/s^2, ``mass`` kg, ``inertia`` kg m^2.

    Returns (code, the state at each sample (S, 6), events (time less ``t0``, kind 0 support / 1 catch-up, axes
    caught up as bits, the piece after it; (E, 4) floats), the state at each event (E, 6), each piece's cells as
    offsets into a pool (P + 1,) and the pool, the axes' mode at the start (+-1 slipping that way, 0 sticking; (2,)),
    the wheels' work and the friction's dissipation (J)). ``code`` is one of :data:`REASONS`' indices; only 0 (it
    glides) comes with the rest filled."""
    S = taus.shape[0]
    none6 = np.zeros((0, 6))
    noneE = np.zeros((0, 4))
    nonei = np.zeros(0, np.int64)
    mode = np.zeros(2, np.int64)
    vx, vy, om = y[3], y[4], y[5]
    speed = max(1e-3, math.sqrt(vx * vx + vy * vy))
    if abs(om) * radius > 1e-12 * speed:
        return _TURNS, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    if not (mu > 0.0 and mu_s > 0.0 and gravity > 0.0):
        return _NO_GRIP, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    ids = _within(points, order, start, lo0, lo1, size, nx, ny, present, y[0], y[1], radius)
    if ids.shape[0] == 0:
        return _NO_SUPPORT, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    # the wheels' velocity: a cell under the footprint now's (every cell under it in the window must have it)
    c_, s_ = math.cos(y[2]), math.sin(y[2])
    K = normals.shape[0]
    wn = np.empty((K, 2))
    for q in range(K):
        wn[q, 0] = c_ * normals[q, 0] - s_ * normals[q, 1]
        wn[q, 1] = s_ * normals[q, 0] + c_ * normals[q, 1]
    under = -1
    for c in range(ids.shape[0]):
        if _inside(positions[ids[c], 0] - y[0], positions[ids[c], 1] - y[1], wn, offsets):
            under = ids[c]
            break
    if under < 0:
        return _NO_SUPPORT, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    u = V[under]
    # the axes: slip, mode, catch-up time
    g = mu * gravity
    W = mass * gravity
    v0 = np.empty(2)
    uk = np.empty(2)
    acc = np.zeros(2)
    tk = np.full(2, -1.0)
    e = (e1, e2)
    top = 1e-3
    for k in range(2):
        v0[k] = vx * e[k][0] + vy * e[k][1]
        uk[k] = u[0] * e[k][0] + u[1] * e[k][1]
        top = max(top, abs(v0[k]), abs(uk[k]))
    # the engine's rule: zero slip below 1e-9 of the speed scale plus what the slip moves in an event time's
    # uncertainty (stick_modes._slip_tol); a slip between half its least and twice its most is not called here
    least = 0.5e-9 * top
    accel = 2.0 * mu_s * W * math.sqrt(1.0 + radius * radius) * max(1.0 / mass, 1.0 / inertia)
    most = 2.0 * (1e-9 * 2.0 * top + accel * (16.0 * 2.220446049250313e-16 * abs(t0 + T) + 2e-13))
    for k in range(2):
        s = v0[k] - uk[k]
        if abs(s) <= least:
            v0[k] = uk[k]  # the twist projected onto the sticking wheels
        elif abs(s) > most:
            mode[k] = 1 if s > 0 else -1
            acc[k] = -mode[k] * g
            tk[k] = abs(s) / g
        else:
            return _UNSURE_SLIP, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    if 0 <= tk[0] and 0 <= tk[1] and MERGE * max(1.0, t0 + T) < abs(tk[0] - tk[1]) < APART:
        return _CLOSE, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    # how far the centre can go: each axis' position is monotone between its turn (speed zero) and its catch-up
    reach = 0.0
    for k in range(2):
        far = 0.0
        for tau in (0.0, T, min(max(tk[k], 0.0), T), min(max(-v0[k] / acc[k] if acc[k] != 0.0 else 0.0, 0.0), T)):
            x, _ = _axis(v0[k], acc[k], tk[k], uk[k], tau)
            far = max(far, abs(x))
        reach += far
    ids = _within(points, order, start, lo0, lo1, size, nx, ny, present, y[0], y[1], radius + reach + 1e-9)
    # the phases: the window cut at each axis' catch-up
    cuts = np.empty(4)
    cuts[0], nc = 0.0, 1
    for k in range(2):
        if 0.0 < tk[k] < T:
            cuts[nc] = tk[k]
            nc += 1
    cuts[nc] = T
    nc += 1
    cuts = np.sort(cuts[:nc])
    # each edge margin of each cell: o - n.(p - X) with n the edge's world normal, a quadratic in tau by phase
    m = ids.shape[0]
    roots = np.empty(m * K * 2 * (nc - 1) + 2)
    nr = 0
    for c in range(m):
        px, py = positions[ids[c], 0] - y[0], positions[ids[c], 1] - y[1]
        for q in range(K):
            g1 = wn[q, 0] * e1[0] + wn[q, 1] * e1[1]
            g2 = wn[q, 0] * e2[0] + wn[q, 1] * e2[1]
            A0 = offsets[q] - (wn[q, 0] * px + wn[q, 1] * py)
            for ph in range(nc - 1):
                mid = 0.5 * (cuts[ph] + cuts[ph + 1])
                a1, b1, c1 = _phase(v0[0], acc[0], tk[0], uk[0], mid)
                a2, b2, c2 = _phase(v0[1], acc[1], tk[1], uk[1], mid)
                # (from just before the start: a cell on an edge at the start is the engine's to call)
                nr = _roots(A0 + g1 * a1 + g2 * a2, g1 * b1 + g2 * b2, g1 * c1 + g2 * c2,
                            -APART if ph == 0 else cuts[ph], cuts[ph + 1], roots, nr)
    roots = np.sort(roots[:nr])
    # one event per crossing time; a crossing too near the window's ends, a catch-up or another crossing is not
    # called here
    tol = MERGE * max(1.0, t0 + T)
    times = np.empty(nr + 1)
    nt = 0
    for r in range(nr):
        t = roots[r]
        if t < APART or t > T - APART:
            return _CLOSE, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
        for k in range(2):
            if 0 <= tk[k] < T and abs(t - tk[k]) < APART:
                return _CLOSE, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
        if nt and t - times[nt - 1] <= tol:
            continue
        if nt and t - times[nt - 1] < APART:
            return _CLOSE, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
        times[nt] = t
        nt += 1
    times[nt] = T
    # the cells under the footprint between crossings (all margins > 0 midway), a piece where they change
    pool = np.empty(m * (nt + 1), np.int64)
    offs = np.zeros(nt + 2, np.int64)
    first = np.empty(nt + 1)  # each piece's start (tau)
    npieces = 0
    ev = np.empty((nt + 2, 4))
    ne = 0
    lo = 0.0
    for j in range(nt + 1):
        hi = times[j]
        mid = 0.5 * (lo + hi)
        x1, _ = _axis(v0[0], acc[0], tk[0], uk[0], mid)
        x2, _ = _axis(v0[1], acc[1], tk[1], uk[1], mid)
        Xx, Xy = x1 * e1[0] + x2 * e2[0], x1 * e1[1] + x2 * e2[1]
        at = offs[npieces]
        n = 0
        for c in range(m):
            if _inside(positions[ids[c], 0] - y[0] - Xx, positions[ids[c], 1] - y[1] - Xy, wn, offsets):
                pool[at + n] = ids[c]
                n += 1
        same = npieces > 0 and n == offs[npieces] - offs[npieces - 1]
        if same:
            for a in range(n):
                if pool[at + a] != pool[offs[npieces - 1] + a]:
                    same = False
                    break
        if not same:
            if n == 0:
                return _NO_SUPPORT, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
            offs[npieces + 1] = at + n
            first[npieces] = lo
            if npieces:
                ev[ne, 0], ev[ne, 1], ev[ne, 2], ev[ne, 3] = lo, 0.0, 0.0, npieces
                ne += 1
            npieces += 1
        lo = hi
    # every cell that comes under the footprint moves at the wheels' velocity (the others push nothing)
    for r in range(offs[npieces]):
        if V[pool[r], 0] != u[0] or V[pool[r], 1] != u[1]:
            return _NOT_UNIFORM, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    # each piece's normal forces (eq. 7 by the 3 x 3 moment system, every cell in contact), over its span
    for p in range(npieces):
        a, b = offs[p], offs[p + 1]
        cnt = b - a
        if cnt < 3:
            return _LINE, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
        ox, oy = 0.0, 0.0
        for r in range(a, b):
            ox += positions[pool[r], 0]
            oy += positions[pool[r], 1]
        ox, oy = ox / cnt, oy / cnt
        M = np.zeros((3, 3))
        for r in range(a, b):
            bx, by = positions[pool[r], 0] - ox, positions[pool[r], 1] - oy
            row = (1.0, bx, by)
            for i in range(3):
                for jj in range(3):
                    M[i, jj] += row[i] * row[jj]
        sxx, syy, sxy = M[1, 1] / cnt, M[2, 2] / cnt, M[1, 2] / cnt
        small = 0.5 * (sxx + syy) - math.sqrt(0.25 * (sxx - syy) ** 2 + sxy * sxy)
        if not small > 1e-6 * (sxx + syy):
            return _LINE, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
        Minv = np.linalg.inv(M)
        p_lo = first[p]
        p_hi = first[p + 1] if p + 1 < npieces else T
        for r in range(a, b):
            bx, by = positions[pool[r], 0] - ox, positions[pool[r], 1] - oy
            q0 = Minv[0, 0] + Minv[0, 1] * bx + Minv[0, 2] * by  # N = W (q0 + q1 X + q2 Y), X local (eq. 7)
            q1 = Minv[1, 0] + Minv[1, 1] * bx + Minv[1, 2] * by
            q2 = Minv[2, 0] + Minv[2, 1] * bx + Minv[2, 2] * by
            for ph in range(nc - 1):
                lo_, hi_ = max(p_lo, cuts[ph]), min(p_hi, cuts[ph + 1])
                if hi_ < lo_:
                    continue
                mid = 0.5 * (cuts[ph] + cuts[ph + 1])
                a1, b1, c1 = _phase(v0[0], acc[0], tk[0], uk[0], mid)
                a2, b2, c2 = _phase(v0[1], acc[1], tk[1], uk[1], mid)
                # N / W as A + B tau + C tau^2 over the phase; its least over [lo_, hi_]
                h1, h2 = q1 * e1[0] + q2 * e1[1], q1 * e2[0] + q2 * e2[1]
                A = q0 + q1 * (y[0] - ox) + q2 * (y[1] - oy) + h1 * a1 + h2 * a2
                B = h1 * b1 + h2 * b2
                C = h1 * c1 + h2 * c2
                least_n = min(A + B * lo_ + C * lo_ * lo_, A + B * hi_ + C * hi_ * hi_)
                if C > 0.0:
                    tv = -B / (2.0 * C)
                    if lo_ < tv < hi_:
                        least_n = min(least_n, A + B * tv + C * tv * tv)
                if not least_n > LIFT:
                    return _LIFTS, none6, noneE, none6, nonei, nonei, mode, 0.0, 0.0
    # the catch-ups, in time order among the support events
    for k in range(2):
        if 0.0 < tk[k] < T:
            bits = 1 << k
            if k == 1 and 0.0 < tk[0] < T and abs(tk[1] - tk[0]) <= tol:
                ev[ne - 1, 2] = 3.0  # both axes at once: one event
                continue
            piece = 0
            for p in range(npieces):
                if first[p] <= tk[k]:
                    piece = p
            ev[ne, 0], ev[ne, 1], ev[ne, 2], ev[ne, 3] = tk[k], 1.0, bits, piece
            ne += 1
    ev = ev[:ne]
    ev = ev[np.argsort(ev[:, 0], kind="mergesort")]
    states = np.empty((ne, 6))
    for r in range(ne):
        _state(v0, acc, tk, uk, e1, e2, y, ev[r, 0], states[r])
    out = np.empty((S, 6))
    for r in range(S):
        _state(v0, acc, tk, uk, e1, e2, y, taus[r], out[r])
    work, loss = 0.0, 0.0
    for k in range(2):
        if mode[k] != 0:
            span = min(tk[k], T)
            work += -mode[k] * mu * W * uk[k] * span  # the slipping wheels' push times their speed
            loss += mu * W * (abs(v0[k] - uk[k]) * span - 0.5 * g * span * span)  # mu W |s_k| integrated
    return _OK, out, ev, states, offs[:npieces + 1].copy(), pool, mode, work, loss


@njit(cache=True)
def _state(v0, acc, tk, uk, e1, e2, y, tau, out):
    """The state at ``tau`` s into the window into ``out`` (6,)."""
    x1, w1 = _axis(v0[0], acc[0], tk[0], uk[0], tau)
    x2, w2 = _axis(v0[1], acc[1], tk[1], uk[1], tau)
    out[0] = y[0] + x1 * e1[0] + x2 * e2[0]
    out[1] = y[1] + x1 * e1[1] + x2 * e2[1]
    out[2] = y[2]
    out[3] = w1 * e1[0] + w2 * e2[0]
    out[4] = w1 * e1[1] + w2 * e2[1]
    out[5] = 0.0


class GlideStepper:
    """Writes the windows of stick-slip parcels that translate over one uniform wheel field (module docstring) as the
    event-driven engine's trajectories, and hands every other parcel back.

    It serves a contact layer whose every cell has both wheels, along the same two orthogonal directions in every
    cell (:meth:`serves`); convex footprints only.

    Args:
        cells: the contact layer.
        specs: every parcel of the plant.
        gravity: m/s^2.
    """

    def __init__(self, cells, specs, gravity: float):
        self.cells = cells
        self.gravity = float(gravity)
        self.specs = list(specs)
        self.reasons = np.zeros(len(REASONS), dtype=np.int64)
        """How many windows each :data:`REASONS` ended with (index 0: written here)."""
        self._outline: dict[int, tuple | None] = {}
        dirs = np.asarray(cells.drive_directions, dtype=float)
        self.e1, self.e2 = np.ascontiguousarray(dirs[0, 0]), np.ascontiguousarray(dirs[0, 1])

    @staticmethod
    def serves(cells) -> bool:
        """Whether every cell has both wheels along the same two orthogonal unit directions."""
        dirs = np.asarray(cells.drive_directions, dtype=float)
        if len(dirs) == 0 or not np.asarray(cells.wheel_active, dtype=bool).all():
            return False
        if not (dirs == dirs[0]).all():
            return False
        e1, e2 = dirs[0]
        unit = abs(float(e1 @ e1) - 1.0) <= 1e-12 and abs(float(e2 @ e2) - 1.0) <= 1e-12
        return unit and abs(float(e1 @ e2)) <= 1e-12

    def _footprint(self, i: int):
        """Parcel ``i``'s body-frame half-planes (normals, offsets), or None for a footprint that is not convex."""
        if i not in self._outline:
            spec = self.specs[i]
            if spec.convex:
                normals, offsets = spec.halfplanes
                self._outline[i] = (np.ascontiguousarray(normals, dtype=float).reshape(-1, 2),
                                    np.ascontiguousarray(offsets, dtype=float).reshape(-1))
            else:
                self._outline[i] = None
        return self._outline[i]

    def step(self, models, idx: list[int], ys, t: float, te: float, samples: np.ndarray) -> tuple[dict, list[int]]:
        """Write the windows ``t`` to ``te`` (s) of those of parcels ``idx`` (states ``ys[i]``, no other parcel
        within reach) that glide, sampled at ``samples`` (the window's ends among them; as the engine takes them).
        Returns {parcel: Trajectory} of those and the parcels left for the event-driven engine. ``models`` are the
        plant's models under the window's wheel velocities; each written parcel's wheel memory is left as the engine
        leaves it (its last support's wheels, no impulse, sticking where its mode sticks)."""
        if not idx:  # (the plant makes a stepper only for a contact layer it serves: the layer does not change)
            return {}, list(idx)
        grid = self.cells.grid
        base, made = models.base, models.made
        V = np.ascontiguousarray(models.velocities, dtype=float)
        taus = np.ascontiguousarray(samples - t, dtype=float)
        done: dict[int, Trajectory] = {}
        rest = []
        for i in idx:
            foot = self._footprint(i)
            model = base[i]
            if foot is None:
                rest.append(i)
                continue
            spec = self.specs[i]
            present = model.present if model.present is not None else ALL_PRESENT
            code, out, ev, states, offs, pool, mode, work, loss = glide_window(
                grid.points, grid.order, grid.start, float(grid.lo[0]), float(grid.lo[1]), float(grid.size),
                int(grid.shape[0]), int(grid.shape[1]), present, self.cells.positions, V, self.e1, self.e2,
                np.ascontiguousarray(ys[i], dtype=float), float(t), float(te - t), taus, foot[0], foot[1],
                float(spec.radius), float(spec.mu), float(spec.mu if spec.mu_static is None else spec.mu_static),
                self.gravity, float(spec.mass), float(spec.inertia))
            self.reasons[code] += 1
            if code != _OK:
                rest.append(i)
                continue
            done[i] = self._trajectory(i, model, made.get(i), ys[i], samples, out, t, te, ev, states, offs, pool,
                                       mode, work, loss)
        return done, rest

    def _trajectory(self, i, model, copy, y, samples, out, t, te, ev, states, offs, pool, mode, work, loss):
        """Parcel ``i``'s window from state ``y`` as the engine's :class:`Trajectory`, from :func:`glide_window`'s
        arrays."""
        spec = self.specs[i]
        pieces = [tuple(pool[offs[p]:offs[p + 1]].tolist()) for p in range(len(offs) - 1)]
        axes = list(mode.tolist())
        events: list[Event] = []
        mode_events: list[tuple] = []
        piece = 0
        for (tau, kind, bits, to), at in zip(ev.tolist(), states.tolist()):
            when = t + tau
            if kind == 0.0:  # a support event: cells entering or leaving, every one in contact
                old, new = pieces[piece], pieces[int(to)]
                events.append(Event.support_between(when, tuple(at), (old, old), (new, new)))
                piece = int(to)
                continue
            cells = pieces[piece]
            before = tuple(axes) * len(cells)
            caught = [k for k in range(2) if int(bits) >> k & 1]
            for k in caught:
                axes[k] = 0
            after = tuple(axes) * len(cells)
            mode_events.append((when, "slip", before, after))
            events.append(Event(when, "stick", tuple(at),
                                message=" ".join(f"{c}:{k}" for c in cells for k in range(2) if k in caught)))
        last = pieces[piece]
        memory = model.contact_memory  # (shared with the copies made from it)
        keys = [(c, k) for c in last for k in range(2)]
        memory["lam"] = dict.fromkeys(keys, 0.0)
        memory["stuck"] = {key: axes[key[1]] == 0 for key in keys}
        y0, y1 = y, out[-1]  # (the energy at the start before the twist is projected, as the engine counts it)
        stats = {"wheel_work": float(work), "friction_dissipation": float(loss), "step_dissipation": 0.0,
                 "contact_work": 0.0, "sweeps_max": 0, "unconverged_steps": 0,
                 "kinetic_start": 0.5 * float(spec.mass * (y0[3] ** 2 + y0[4] ** 2) + spec.inertia * y0[5] ** 2),
                 "kinetic_end": 0.5 * spec.mass * float(y1[3] ** 2 + y1[4] ** 2),
                 "mode_changes": len(mode_events), "mode_events": mode_events,
                 "pieces_cached": 0 if copy is None else copy.pieces_cached, "solves": model.solves}
        return Trajectory(np.asarray(samples, dtype=float), out, events, "completed", float(te),
                          len(pieces) + len(mode_events), 0, stats)


__all__ = ["GlideStepper", "glide_window", "REASONS"]
