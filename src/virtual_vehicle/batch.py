"""Quiet windows stepped together: many separately moving parcels in one vectorised Dormand-Prince step.

Units: SI (m, s, kg, N, rad).

A networked run advances the plant one control tick at a time, and most ticks of most parcels are *quiet*: no cell
enters or leaves the footprint, none lifts off or touches down, and the centre of mass stays inside the supports. For
such a window the event-driven engine (:func:`~virtual_vehicle.dynamics.integrate`) finds no event and takes one
DOP853 step over it, but spends most of a millisecond setting that step up. :class:`QuietStepper` proves windows
quiet and takes that same step (same tableau, same error test, same dense output) for all quiet parcels at once,
with each parcel's piece constants (:func:`~virtual_vehicle.dynamics.constants_row`) as arrays.

The proof is a bound, not a sample. Let ``r`` bound how far any point of a parcel can move in the window
(:func:`~virtual_vehicle.collide.reach_bounds`, from the friction law alone; the planner has already ruled out
pushes from other parcels). At an *anchor* state the stepper measures:

- ``clear``: the smallest ``|margin|`` of any cell near the footprint (m), at most the search buffer. A margin is
  1-Lipschitz in how far the footprint points move (a cell crosses the outline only where a footprint point passes
  over it), so no cell enters or leaves while the footprint points have moved less than ``clear`` since the anchor.
- ``slack``: how far (m) the centre of mass can move before any spring force (affine in it, gradient ``G_k``) or any
  supporting half-plane changes sign: ``min(|N_k| / |G_k|, hull slack)``, less rounding noise.

Footprint points have moved at most ``P = |dX_c| + |d theta| R`` since the anchor; the window is quiet when
``clear > P + r`` and ``slack > |dX_c| + r``. Then the piece holds throughout and the motion is one smooth ODE.
Windows not proven quiet, and quiet ones whose single step fails the error test, go to the event-driven engine.
An anchor lasts while its parcel's windows stay quiet; the constants are remade when the wheel velocities under the
supports change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import DOP853

from .collide import reach_bounds
from .contact import SupportSolution
from .dynamics import (_NOISE, ROW_LENGTH, ParcelModel, Trajectory, accelerations, constants_row)
from .errors import TippingError
from .parcel import footprint_margins


@dataclass
class _Anchor:
    """Where a parcel's clearances were measured, and the piece that holds until they run out."""

    pose: np.ndarray  # (3,) x, y (m), theta (rad)
    clear: float  # m
    slack: float  # m
    support: np.ndarray  # cell ids
    solution: SupportSolution
    geometry: object  # the parcel's shared cache of solved supports (for its count of solves)
    velocities: np.ndarray | None = None  # (len(support), 2) m/s the row was made with
    row: tuple[float, ...] | None = None


def anchor(model: ParcelModel, y: np.ndarray, length: float) -> _Anchor | None:
    """The anchor of ``model``'s parcel at state ``y``; None when it has no piece there (it tips). ``length`` (m) is
    the scale of rounding noise in positions (the array's largest coordinate, at least 1 m)."""
    try:
        piece = model.piece_at(y)
    except TippingError:
        return None
    spec, cells = model.spec, model.cells
    sol = piece.solution
    buffer = max(cells.pitch, 0.25 * spec.radius)
    ids = np.asarray(cells.tree.query_ball_point(np.asarray(y[:2], dtype=float), spec.radius + buffer), dtype=int)
    if model.present is not None and len(ids):
        ids = ids[model.present[ids]]
    length = max(length, spec.radius)
    clear = buffer
    if len(ids):
        clear = min(clear, float(np.min(np.abs(footprint_margins(spec, y, cells.positions[ids])))))
    clear -= _NOISE * length
    xi = np.asarray(y[:2], dtype=float) - sol.origin
    springs = _room(np.abs(sol.spring_values(xi)) - _NOISE * model.weight, sol.basis @ sol.plane_lin)
    hull = _room(sol.hull_slack(xi) - _NOISE * length * np.linalg.norm(sol.hull_normals, axis=1), sol.hull_normals)
    slack = float(min(np.min(springs, initial=np.inf), np.min(hull, initial=np.inf)))
    return _Anchor(np.array(y[:3], dtype=float), clear, slack, piece.support, sol, model._geometry)


def _room(values: np.ndarray, gradients: np.ndarray) -> np.ndarray:
    """How far (m) the centre of mass can move before affine functions with these ``values`` (> 0 is clear) and
    ``gradients`` (k, 2) reach zero: inf for a constant one that is clear, -inf for one that is not."""
    norm = np.linalg.norm(gradients, axis=1)
    return np.where(norm > 0, values / np.where(norm > 0, norm, 1.0), np.where(values > 0, np.inf, -np.inf))


class QuietStepper:
    """Steps the quiet windows of separately moving parcels together (see the module docstring).

    Args:
        specs: every parcel of the plant.
        law: ``"viscous"`` or ``"coulomb"`` (for the reach bound).
        mu_max: each parcel's largest friction coefficient.
        gravity: m/s^2.
        rtol, atol: the event-driven engine's tolerances, applied to the single step exactly as it applies them.
    """

    def __init__(self, specs, law: str, mu_max, gravity: float, rtol: float, atol: float):
        self.length: float | None = None  # m, set from the array on first use
        self.law = law
        self.gravity = gravity
        self.rtol, self.atol = rtol, atol
        self.radius = np.array([s.radius for s in specs])
        self.lever_mu = np.array([m * (1.0 + s.mass * s.radius ** 2 / s.inertia) for s, m in zip(specs, mu_max)])
        self.anchors: dict[int, _Anchor] = {}

    def forget(self, i: int | None = None) -> None:
        """Drop parcel ``i``'s anchor (all anchors when None): it was moved another way, or the array changed."""
        if i is None:
            self.anchors.clear()
        else:
            self.anchors.pop(i, None)

    def _anchor(self, i, models, y) -> _Anchor | None:
        if self.length is None:
            self.length = max(1.0, float(np.max(np.abs(models[i].cells.positions))))
        a = anchor(models[i], y, self.length)
        if a is None:
            self.anchors.pop(i, None)
        else:
            self.anchors[i] = a
        return a

    def _quiet(self, idx: list[int], Y: np.ndarray, anchors: list[_Anchor], window: float,
               wheel_speed: float) -> np.ndarray:
        """Which of the parcels ``idx`` at states ``Y`` are proven quiet for ``window`` s from their anchors."""
        R = self.radius[idx]
        P0 = np.array([a.pose for a in anchors])
        moved = np.hypot(Y[:, 0] - P0[:, 0], Y[:, 1] - P0[:, 1])
        swept = moved + np.abs(Y[:, 2] - P0[:, 2]) * R
        s0 = np.hypot(Y[:, 3], Y[:, 4]) + np.abs(Y[:, 5]) * R
        r = reach_bounds(s0, self.lever_mu[idx], window, law=self.law, gravity=self.gravity,
                         wheel_speed=wheel_speed)[0]
        clear = np.array([a.clear for a in anchors])
        slack = np.array([a.slack for a in anchors])
        return (clear > swept + r) & (slack > moved + r)

    def step(self, models, base, idx: list[int], ys, velocities: np.ndarray, t: float, te: float,
             samples: np.ndarray) -> tuple[dict[int, Trajectory], list[int]]:
        """Advance the parcels ``idx`` (states ``ys[i]``, no other parcel within reach) from ``t`` to ``te`` (s)
        under contact-layer ``velocities`` (m/s): returns the trajectories (sampled at ``samples``) of those stepped
        here and the parcels left for the event-driven engine. ``models[i]`` is parcel i's model under these
        velocities (asked for only to make an anchor), ``base[i]`` any model of it (for the friction constants)."""
        if not idx:
            return {}, []
        window = te - t
        wheel_speed = float(np.max(np.hypot(velocities[:, 0], velocities[:, 1]))) if len(velocities) else 0.0
        Y = np.array([ys[i] for i in idx], dtype=float)
        Y = np.where(np.abs(Y) < 1e-100, 0.0, Y)  # as integrate() does
        anchors = [self.anchors.get(i) for i in idx]
        for k, i in enumerate(idx):
            if anchors[k] is None:
                anchors[k] = self._anchor(i, models, Y[k])
        have = np.array([a is not None for a in anchors])
        ok = np.zeros(len(idx), dtype=bool)
        if have.any():
            sel = np.flatnonzero(have)
            ok[sel] = self._quiet([idx[k] for k in sel], Y[sel], [anchors[k] for k in sel], window, wheel_speed)
        for k in np.flatnonzero(have & ~ok):  # an old anchor may have run out: measure again where the parcel is
            a = anchors[k]
            if not np.array_equal(a.pose, Y[k, :3]):
                anchors[k] = a = self._anchor(idx[k], models, Y[k])
                ok[k] = a is not None and bool(self._quiet([idx[k]], Y[k:k + 1], [a], window, wheel_speed)[0])
        quiet = np.flatnonzero(ok)
        rest = [idx[k] for k in np.flatnonzero(~ok)]
        if not len(quiet):
            return {}, rest
        rows = []
        for k in quiet:
            a = anchors[k]
            v = velocities[a.support]
            if a.row is None or not np.array_equal(v, a.velocities):
                model = base[idx[k]]
                a.velocities = v.copy()
                a.row = constants_row(model.constants_for(a.support, a.solution, v), a.solution.origin,
                                      model.spec.mass, model.spec.inertia)
            rows.append(a.row)
        y_new, accepted, dense, evals = dop853_step(rows, Y[quiet], window, self.rtol, self.atol)
        inside = samples[(samples > t) & (samples < te)]
        states_inside = dense(inside - t) if len(inside) else None
        out = {}
        for n, k in enumerate(quiet):
            i = idx[k]
            if not accepted[n]:
                rest.append(i)
                continue
            end = Y[k] + (y_new[n] - Y[k])  # the dense output at the step's end, as the event engine samples it
            states = [Y[k], *(states_inside[:, n] if states_inside is not None else ()), end]
            out[i] = Trajectory(np.concatenate([[t], inside, [te]]), np.array(states), [], "completed", te, 1,
                                evals + (3 if len(inside) else 0),
                                {"solves": anchors[k].geometry.solves})
        return out, rest


_FEW = 12
"""Up to this many parcels the right-hand side is evaluated parcel by parcel in plain floats (cheaper than array
operations on a handful of entries); above it, on arrays."""


def _derivatives(rows, columns, Y: np.ndarray) -> np.ndarray:
    """(n, 6) state derivatives of n parcels at states ``Y`` (n, 6): ``rows`` their constants, ``columns`` the same
    as arrays (None below ``_FEW`` parcels)."""
    if columns is None:
        return np.array([(y[3], y[4], y[5], *accelerations(row, y[0], y[1], y[3], y[4], y[5]))
                         for row, y in zip(rows, Y.tolist())])
    ax, ay, alpha = accelerations(columns, Y[:, 0], Y[:, 1], Y[:, 3], Y[:, 4], Y[:, 5])
    return np.column_stack((Y[:, 3], Y[:, 4], Y[:, 5], ax, ay, alpha))


def _combine(a: np.ndarray, K: np.ndarray) -> np.ndarray:
    """sum_s a[s] K[s] for stages K (s, n, 6)."""
    return (a @ K.reshape(len(a), -1)).reshape(K.shape[1:])


def dop853_step(rows, Y: np.ndarray, h: float, rtol: float, atol: float):
    """One step of length ``h`` (s) of scipy's DOP853 for n independent parcels at once.

    ``rows`` are the parcels' :func:`~virtual_vehicle.dynamics.constants_row` tuples, ``Y`` (n, 6) their states.
    Returns the new states (n, 6), which parcels pass DOP853's error test (its norm, per parcel, below 1: then
    scipy, started with this step, takes exactly it), a function giving the dense output at times ``tau`` (s, from
    the step's start) as (len(tau), n, 6), and the evaluations made per parcel.
    """
    if any(len(row) != ROW_LENGTH for row in rows):
        raise ValueError(f"every row of constants must have {ROW_LENGTH} entries")
    columns = tuple(np.array(rows).T) if len(rows) > _FEW else None
    n_stages = DOP853.n_stages
    K = np.empty((DOP853.D.shape[1], len(Y), 6))
    K[0] = _derivatives(rows, columns, Y)
    for s in range(1, n_stages):
        K[s] = _derivatives(rows, columns, Y + _combine(DOP853.A[s, :s], K[:s]) * h)
    y_new = Y + h * _combine(DOP853.B, K[:n_stages])
    K[n_stages] = _derivatives(rows, columns, y_new)
    scale = atol + np.maximum(np.abs(Y), np.abs(y_new)) * rtol
    err5 = np.sum((_combine(DOP853.E5, K[:n_stages + 1]) / scale) ** 2, axis=1)
    err3 = np.sum((_combine(DOP853.E3, K[:n_stages + 1]) / scale) ** 2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.where((err5 == 0) & (err3 == 0), 0.0, abs(h) * err5 / np.sqrt((err5 + 0.01 * err3) * 6))
    accepted = norm < 1

    def dense(tau_abs):
        for s, a in enumerate(DOP853.A_EXTRA, start=n_stages + 1):
            K[s] = _derivatives(rows, columns, Y + _combine(a[:s], K[:s]) * h)
        delta = y_new - Y
        F = [delta, h * K[0] - delta, 2 * delta - h * (K[n_stages] + K[0]),
             *(h * _combine(row, K) for row in DOP853.D)]
        out = []
        for tau in np.atleast_1d(tau_abs):
            x = tau / h
            y = np.zeros_like(Y)
            for j, f in enumerate(reversed(F)):
                y += f
                y *= x if j % 2 == 0 else 1 - x
            out.append(y + Y)
        return np.array(out)

    return y_new, accepted, dense, n_stages + 1
