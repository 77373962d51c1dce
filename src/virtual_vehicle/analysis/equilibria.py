"""Equilibria of the force and torque a wheel-velocity field induces on a parcel, and their stability (paper
Section 5: "find the equilibria of the induced force field and their stability").

Units: SI (m, rad, N, N m, N/m).

Within one support set (a piece, paper 4.5) the force is affine in the centre of mass, ``f = a X + b`` (eqs. 23,
29), and neither force nor torque depends on the heading: the heading only decides which cells are under the
parcel. So, for a heading ``theta``:

- a *translational* equilibrium of a piece is ``X* = -a^{-1} b``, valid when the piece at ``(X*, theta)`` is that
  piece (checked), and its stiffness is ``-a`` (N/m); it is restoring when the eigenvalues of ``a / m`` have
  negative real parts. Under the viscous law the parcel's own motion is damped (eqs. 33, 38), so a restoring
  equilibrium is asymptotically stable; the paper's Coulomb law has no damping, so it is only marginally stable
  (the parcel oscillates about it, as in the paper's 2x2 example).
- the torque at ``X*(theta)`` then changes with the heading only where a cell enters or leaves the footprint. An
  equilibrium heading is where it changes sign: continuously, or by a jump at a support change (the parcel is then
  held at that heading, a sliding mode). It is stable when the torque goes from positive to negative as the heading
  increases (it turns the parcel back), unstable otherwise. A branch whose torque vanishes over a range of headings
  is neutral in heading (the 2x2 inward field: zero torque).

:func:`equilibria` samples headings and centre-of-mass positions to find the pieces, solves each piece exactly,
follows branches across headings and bisects each sign change of the torque to the heading's resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virtual_vehicle.engine.dynamics import ParcelModel
from virtual_vehicle.errors import TippingError
from virtual_vehicle.model.layout import CellArray
from virtual_vehicle.model.parcel import ParcelSpec
from virtual_vehicle.physics.laws import FrictionLaw


@dataclass
class Equilibrium:
    """An equilibrium pose of a parcel in a field.

    Attributes:
        pose: (x, y, theta) m, m, rad. For a heading-neutral branch, theta is the middle of ``heading_range``.
        stiffness: (2, 2) translational stiffness ``-a`` (N/m) of the piece: force = -stiffness @ displacement.
        torque_jump: (torque just below, just above) the equilibrium heading (or its range), N m.
        translation: ``"stable"`` (restoring and damped), ``"marginal"`` (restoring, undamped: Coulomb),
            ``"neutral"`` (no stiffness along some direction: a line of equilibria, restoring across it) or
            ``"unstable"``.
        rotation: ``"stable"`` (the torque turns the parcel back toward it), ``"unstable"`` or ``"neutral"``. A
            branch with zero torque over ``heading_range`` is stable when the torque on either side points into
            the range, unstable when it points out, else neutral.
        support: ids of the supporting cells.
        heading_range: (lo, hi) rad of a zero-torque branch (lo may be negative for a range across 0); None
            otherwise.
    """

    pose: tuple[float, float, float]
    stiffness: np.ndarray
    torque_jump: tuple[float, float]
    translation: str
    rotation: str
    support: tuple[int, ...]
    heading_range: tuple[float, float] | None = None

    @property
    def stable(self) -> bool:
        """Restoring in translation (damped or not) and not unstable in heading."""
        return self.translation in ("stable", "marginal", "neutral") and self.rotation != "unstable"


class _Field:
    """The parcel in the field, for static analysis (zero twist)."""

    def __init__(self, cells, spec, velocities, law, gravity):
        self.model = ParcelModel(cells, spec, velocities, law, gravity)
        self.spec = spec
        self.damped = law.damped
        self.force_tol = 1e-9 * spec.weight(gravity)

    def piece(self, X, theta):
        try:
            return self.model.piece_at(np.array([X[0], X[1], theta, 0.0, 0.0, 0.0]))
        except TippingError:
            return None

    def solve(self, piece, hint):
        """The piece's own equilibrium centre of mass (m) nearest ``hint``: ``a X + b = 0`` solved by least squares
        (a singular ``a`` leaves a line or plane of equilibria, neutral along it), or None when inconsistent."""
        k = piece.constants
        x0 = np.asarray(hint, dtype=float) - piece.solution.origin
        r0 = k.a @ x0 + k.b
        X = x0 - np.linalg.pinv(k.a, rcond=1e-10) @ r0
        if np.linalg.norm(k.a @ X + k.b) > self.force_tol:
            return None
        return piece.solution.origin + X

    def settle(self, X, theta, iterations=12):
        """Follow pieces from X at heading theta to a self-consistent equilibrium: (X*, piece) or None."""
        for _ in range(iterations):
            piece = self.piece(X, theta)
            if piece is None:
                return None
            Xs = self.solve(piece, X)
            if Xs is None:
                return None
            again = self.piece(Xs, theta)
            if again is not None and again.key == piece.key:
                return Xs, piece
            X = Xs
        return None

    def torque(self, X, theta, piece=None):
        piece = piece or self.piece(X, theta)
        y = np.array([X[0], X[1], theta, 0.0, 0.0, 0.0])
        return float(piece.rhs(0.0, y)[5] * self.spec.inertia)

    def translation(self, piece) -> str:
        ev = np.linalg.eigvals(piece.constants.a / self.spec.mass)
        tiny = 1e-9 * max(1.0, float(np.max(np.abs(ev))))
        if np.any(np.abs(ev) <= tiny) and np.all(ev.real <= tiny):
            return "neutral"
        if np.all(ev.real < 0):
            return "stable" if self.damped else "marginal"
        if np.all(np.abs(ev.real) <= 1e-12 * max(1.0, float(np.max(np.abs(ev))))) and np.all(ev.imag != 0):
            return "marginal"
        return "unstable"


def equilibria(cells: CellArray, spec: ParcelSpec, velocities: np.ndarray, law: FrictionLaw, *,
               bounds=None, headings=None, step: float | None = None, gravity: float = 9.81,
               heading_tol: float = 1e-9) -> list[Equilibrium]:
    """Equilibrium poses of ``spec`` in the constant field ``velocities`` ((n, 2) m/s) under ``law``.

    Args:
        bounds: (xmin, ymin, xmax, ymax) m of centre-of-mass positions to search (default: the array's bounds).
        headings: headings (rad, increasing) to sample (default: 73 from 0 to 2 pi).
        step: spacing (m) of the sampled centre-of-mass positions (default: a quarter pitch).
        heading_tol: bisection tolerance of equilibrium headings, rad.

    Returns:
        The equilibria, sorted by position then heading.
    """
    field = _Field(cells, spec, np.asarray(velocities, dtype=float), law, gravity)
    xmin, ymin, xmax, ymax = cells.bounds if bounds is None else bounds
    step = step or cells.pitch / 4
    headings = np.linspace(0.0, 2 * np.pi, 73) if headings is None else np.asarray(headings, dtype=float)
    xs = np.arange(xmin, xmax + 0.5 * step, step)
    ys = np.arange(ymin, ymax + 0.5 * step, step)
    scale = max(spec.radius, cells.pitch)
    # 1. per heading, every piece's own equilibrium
    samples: list[list[tuple[np.ndarray, object, float]]] = []
    for theta in headings:
        found = {}
        for x in xs:
            for y in ys:
                piece = field.piece((x, y), theta)
                if piece is None or piece.key in found:
                    continue
                found[piece.key] = None
                Xs = field.solve(piece, (x, y))
                if Xs is None or not (xmin - step <= Xs[0] <= xmax + step and ymin - step <= Xs[1] <= ymax + step):
                    continue
                again = field.piece(Xs, theta)
                if again is not None and again.key == piece.key:
                    found[piece.key] = (Xs, piece, field.torque(Xs, theta, piece))
        samples.append([v for v in found.values() if v is not None])
    # 2. follow each equilibrium to the next heading (settling into the piece there); a sign change of the torque is
    #    an equilibrium heading
    out: list[Equilibrium] = []
    tau_tol = 1e-9 * spec.weight(gravity) * scale
    for j in range(len(headings) - 1):
        for X0, piece0, tau0 in samples[j]:
            nxt = _torque_at(field, X0, headings[j + 1])
            if nxt is None:
                continue
            X1, tau1 = nxt
            if not ((tau0 > tau_tol and tau1 < -tau_tol) or (tau0 < -tau_tol and tau1 > tau_tol)):
                continue  # no sign change (a zero run is a neutral branch, collected below)
            eq = _bisect(field, headings[j], headings[j + 1], X0, X1, tau0, tau1, heading_tol, tau_tol)
            if eq is not None:
                out.append(eq)
    out.extend(_merge_wrapped(_neutral_branches(field, headings, samples, tau_tol), tau_tol))
    return _unique(out, step)


def _torque_at(field, X, theta):
    """Settle from X at heading theta: (equilibrium X, its torque N m) or None."""
    got = field.settle(X, theta)
    if got is None:
        return None
    Xs, piece = got
    return Xs, field.torque(Xs, theta, piece)


def _bisect(field, lo, hi, Xlo, Xhi, tau_lo, tau_hi, tol, tau_tol):
    """Refine a sign change of the torque between headings lo and hi."""
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        got = field.settle(0.5 * (Xlo + Xhi), mid)
        if got is None:
            return None
        Xm, _ = got
        tau = field.torque(Xm, mid)
        if abs(tau) <= tau_tol:
            return None  # the torque vanishes here: part of a neutral branch, reported as such
        if (tau > 0) == (tau_lo > 0):
            lo, Xlo, tau_lo = mid, Xm, tau
        else:
            hi, Xhi, tau_hi = mid, Xm, tau
    theta = 0.5 * (lo + hi)
    got = field.settle(0.5 * (Xlo + Xhi), theta)
    if got is None:
        return None
    X, piece = got
    rotation = "stable" if tau_lo > 0 > tau_hi else "unstable"
    return Equilibrium((float(X[0]), float(X[1]), float(theta % (2 * np.pi))), -piece.constants.a.copy(),
                       (float(tau_lo), float(tau_hi)), field.translation(piece), rotation,
                       tuple(piece.support.tolist()))


def _neutral_branches(field, headings, samples, tau_tol):
    """Runs of consecutive headings over which an equilibrium's torque stays zero (followed by settling into the
    next heading's piece): one equilibrium each, classified by the torque just outside the run."""
    out = []
    full_turn = abs(headings[-1] - headings[0] - 2 * np.pi) < 1e-9
    seen: set[tuple] = set()
    for j in range(len(headings)):
        for X, piece, tau in samples[j]:
            if abs(tau) > tau_tol or (j, piece.key) in seen:
                continue
            run = [(j, X, piece)]
            seen.add((j, piece.key))
            k, Xk = j, X
            after = None
            while k + 1 < len(headings):
                nxt = field.settle(Xk, headings[k + 1])
                if nxt is None:
                    break
                Xn, pn = nxt
                tn = field.torque(Xn, headings[k + 1], pn)
                if abs(tn) > tau_tol:
                    after = tn
                    break
                k, Xk = k + 1, Xn
                seen.add((k, pn.key))
                run.append((k, Xn, pn))
            if after is None and k + 1 == len(headings) and full_turn:
                got = _torque_at(field, Xk, headings[1])
                after = None if got is None else got[1]
            before_theta = headings[j - 1] if j > 0 else (headings[-2] if full_turn else None)
            got = None if before_theta is None else _torque_at(field, X, before_theta)
            before = None if got is None else got[1]
            rotation = "neutral"  # zero torque over the run; what the sides do decides if it attracts
            if before is not None and after is not None:
                if before > tau_tol and after < -tau_tol:
                    rotation = "stable"
                elif before < -tau_tol and after > tau_tol:
                    rotation = "unstable"
            mid_j, Xm, pm = run[len(run) // 2]
            rng = (float(headings[run[0][0]]), float(headings[run[-1][0]]))
            out.append(Equilibrium((float(Xm[0]), float(Xm[1]), float(headings[mid_j] % (2 * np.pi))),
                                   -pm.constants.a.copy(), (before or 0.0, after or 0.0), field.translation(pm),
                                   rotation, tuple(pm.support.tolist()), rng))
    return out


def _merge_wrapped(eqs: list[Equilibrium], tau_tol: float) -> list[Equilibrium]:
    """A neutral run that ends at 2 pi and one at the same place that starts at 0 are one run across the wrap."""
    two_pi = 2 * np.pi
    ends = [e for e in eqs if e.heading_range and abs(e.heading_range[1] - two_pi) < 1e-9]
    starts = [e for e in eqs if e.heading_range and abs(e.heading_range[0]) < 1e-9]
    out = [e for e in eqs if not any(e is x for x in ends + starts)]
    used = set()
    for a in ends:
        b = next((s for s in starts if id(s) not in used and np.hypot(a.pose[0] - s.pose[0], a.pose[1] - s.pose[1])
                  < 1e-6), None)
        if b is None:
            out.append(a)
            continue
        used.add(id(b))
        before, after = a.torque_jump[0], b.torque_jump[1]
        rotation = ("stable" if before > tau_tol and after < -tau_tol else
                    "unstable" if before < -tau_tol and after > tau_tol else "neutral")
        lo, hi = a.heading_range[0] - two_pi, b.heading_range[1]
        mid = 0.5 * (lo + hi)
        out.append(Equilibrium((b.pose[0], b.pose[1], float(mid % two_pi)), b.stiffness, (before, after),
                               b.translation, rotation, b.support, (float(lo), float(hi))))
    out.extend(s for s in starts if id(s) not in used)
    return out


def _unique(eqs: list[Equilibrium], step: float) -> list[Equilibrium]:
    """Drop repeats (the same pose found from two sides of 0 = 2 pi), sort by position then heading."""
    out: list[Equilibrium] = []
    for e in sorted(eqs, key=lambda e: (round(e.pose[0] / step), round(e.pose[1] / step), e.pose[2])):
        same = [o for o in out if np.hypot(e.pose[0] - o.pose[0], e.pose[1] - o.pose[1]) < 1e-6
                and abs((e.pose[2] - o.pose[2] + np.pi) % (2 * np.pi) - np.pi) < 1e-6 and o.rotation == e.rotation]
        if not same:
            out.append(e)
    return out
