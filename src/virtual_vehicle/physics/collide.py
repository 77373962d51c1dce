"""Parcels among parcels: where two parcels touch, and the impulses that keep them apart.

Units: SI (m, s, kg, N s, rad).

Parcels are rigid plates sliding on the array. Where two touch they push each other along the contact normal,
inelastically (no bounce: cardboard and totes), and rub with Coulomb friction of coefficient ``mu`` (dimensionless)
across it. Contacts are resolved at the velocity level every time step ``h`` (the time-stepping scheme of Stewart &
Trinkle 1996 / Anitescu & Potra 1997, with "speculative" contacts):

* Contacts come from a Box2D-style manifold between the parcels' convex parts (a non-convex outline is cut into
  triangles): the reference face is the face, of either part, along whose outward normal the other part lies
  farthest out (separating-axis test); the other part's most opposed edge, clipped to the face, gives up to two
  points within ``margin`` of the face's line, each with the face's unit normal ``n`` (from ``j``, the face's
  parcel, toward ``i``) and gap ``g`` (m; negative when overlapping).
* Normal impulse ``lam_n >= 0`` on ``i`` at the point ``p`` along ``n`` (and its opposite on ``j``), complementary to
  ``v_n+ >= -g / h``: the relative normal velocity after the step may close the gap, never more. Contact therefore
  starts exactly when the gap closes, however fast the parcels approach.
* Friction impulse ``|lam_t| <= mu lam_n`` against the tangential slip (maximal dissipation).
* ``nu+ = nu_free + M^-1 J^T lam`` for every parcel of the group, then ``x+ = x + h nu+`` (semi-implicit Euler).

Overlap can then only come from linearising a rotation over one step (second order in ``h``); overlap deeper than
``slop`` is pushed back at ``beta (depth - slop) / h``. The run reports the deepest overlap seen
(``max_penetration_m``), which the tests hold below 0.5 mm.

Face normals keep corner-on-corner meetings honest: a corner sliding past another meets the face's line, never
slips inside between two steps. The plant also checks every window's end for overlaps between parcels that were
integrated apart (``undetected_overlaps``, which must stay 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from virtual_vehicle.model.parcel import ParcelSpec
from virtual_vehicle.physics.laws import FrictionLaw, law_named


@dataclass(frozen=True)
class ContactParams:
    """How parcels touch each other.

    Attributes:
        mu: Coulomb friction coefficient between two parcels' sides (dimensionless).
        margin: gap (m) within which a point of one outline and a face of another are a (speculative) contact.
        slop: overlap depth (m) tolerated before it is pushed back.
        beta: fraction of the overlap beyond ``slop`` removed per step.
        window: longest plant window (s) while two parcels could meet before the end of the interval; parcels that
            cannot touch anything within a window are integrated on their own (event-driven), the others together
            at ``dt``.
        min_window: pairs of parcels that could meet within this time (s) are stepped together.
        max_sweeps, tolerance: projected Gauss-Seidel limits (tolerance relative to the largest impulse).
    """

    mu: float = 0.3
    margin: float = 1e-3
    slop: float = 1e-4
    beta: float = 0.2
    window: float = 1.0
    min_window: float = 0.02
    max_sweeps: int = 500
    tolerance: float = 1e-10


@dataclass
class Contact:
    """A point of parcel ``i``'s outline near a face of parcel ``j``: world ``point`` (m), unit ``normal`` from
    ``j`` toward ``i`` (the face's outward normal), ``gap`` (m, along the normal, negative when overlapping);
    ``feature`` names the (part, face, edge, end) it came from, to carry impulses from one step to the next."""

    i: int
    j: int
    feature: tuple
    point: np.ndarray
    normal: np.ndarray
    gap: float


def outline_distance(spec: ParcelSpec, pose, points) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (m, negative inside) from each world point (p, 2) to the outline of ``spec`` at ``pose``, and
    the unit normal (p, 2) along which the point leaves the outline fastest (outside: from the nearest outline point
    toward the point; inside: from the point toward the nearest outline point; on the outline: the edge's outward
    normal).

    >>> from virtual_vehicle.model.parcel import rectangle
    >>> d, n = outline_distance(rectangle(2.0, 1.0, 1.0, 0.5), (0, 0, 0), np.array([[1.5, 0.0], [0.0, 0.4]]))
    >>> d.round(12).tolist(), (n.round(12) + 0.0).tolist()
    ([0.5, -0.1], [[1.0, 0.0], [0.0, 1.0]])
    """
    local, d, _, k, diff, inside, c, s = _edge_distances(spec, pose, points)
    tiny = 1e-12 * max(1.0, spec.radius)
    with np.errstate(invalid="ignore", divide="ignore"):
        n_local = np.where((d > tiny)[:, None], diff / d[:, None] * np.where(inside, -1.0, 1.0)[:, None],
                           spec.halfplanes[0][k])
    return np.where(inside, -d, d), _to_world(n_local, c, s)


def _to_world(v, c, s):
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]])


def _edge_distances(spec: ParcelSpec, pose, points):
    """Points in the body frame, their distance to the outline, to every edge (p, k), the nearest edge, the offset
    from the nearest outline point (p, 2), whether each is inside, and cos/sin of the heading."""
    pts = np.asarray(points, dtype=float)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy = pts[:, 0] - pose[0], pts[:, 1] - pose[1]
    local = np.column_stack([c * dx + s * dy, -s * dx + c * dy])
    a = spec.footprint
    e = np.roll(a, -1, axis=0) - a
    t = np.einsum("pkj,kj->pk", local[:, None, :] - a[None], e) / np.einsum("kj,kj->k", e, e)
    q = a[None] + np.clip(t, 0.0, 1.0)[..., None] * e[None]
    diff = local[:, None, :] - q
    dist = np.hypot(diff[..., 0], diff[..., 1])
    k = np.argmin(dist, axis=1)
    rows = np.arange(len(pts))
    d = dist[rows, k]
    inside = shapely.contains_xy(spec.polygon, local[:, 0], local[:, 1])
    return local, d, dist, k, diff[rows, k], inside, c, s


def convex_parts(spec: ParcelSpec) -> list[np.ndarray]:
    """The footprint as convex pieces in the body frame, counter-clockwise: itself when convex, else its constrained
    Delaunay triangles (shapely). Made once a parcel (:meth:`~virtual_vehicle.model.parcel.ParcelSpec.derived`)."""
    return spec.derived("convex_parts", _split_convex, spec)


def _split_convex(spec: ParcelSpec) -> list[np.ndarray]:
    if spec.convex:
        return [spec.footprint]
    parts = []
    for tri in shapely.get_parts(shapely.constrained_delaunay_triangles(spec.polygon)):
        v = np.asarray(tri.exterior.coords)[:-1]
        if (v[1, 0] - v[0, 0]) * (v[2, 1] - v[0, 1]) - (v[1, 1] - v[0, 1]) * (v[2, 0] - v[0, 0]) < 0:
            v = v[::-1]
        parts.append(v.copy())
    return parts


def _faces(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals and offsets of a counter-clockwise convex polygon's edges."""
    e = np.roll(v, -1, axis=0) - v
    n = np.column_stack([e[:, 1], -e[:, 0]])
    n /= np.hypot(n[:, 0], n[:, 1])[:, None]
    return n, np.einsum("ij,ij->i", n, v)


def convex_manifold(A: np.ndarray, B: np.ndarray, margin: float, faces_a=None, faces_b=None):
    """Contact points between two convex counter-clockwise polygons (world, m), as in Box2D's polygon collider.

    The reference face is the face, of either polygon, along whose outward normal the other polygon lies farthest
    out (the separating-axis test); the incident edge is the other polygon's edge most opposed to it, clipped to the
    reference face's extent (widened by ``margin``); its points within ``margin`` of the face's line are contacts.
    Returns (incident is A, reference face index, incident edge index, [(end, point, gap)], normal from the
    reference polygon toward the incident one), or None when the polygons are farther apart than ``margin``.
    ``faces_a`` / ``faces_b``: the polygons' (normals, offsets) when already known.
    """
    nA, oA = _faces(A) if faces_a is None else faces_a
    nB, oB = _faces(B) if faces_b is None else faces_b
    sepA = np.min(B @ nA.T - oA, axis=0)  # B beyond each face of A
    sepB = np.min(A @ nB.T - oB, axis=0)
    fa, fb = int(np.argmax(sepA)), int(np.argmax(sepB))
    best = max(sepA[fa], sepB[fb])
    if best > margin:
        return None
    if sepB[fb] >= sepA[fa] - 1e-6 * margin:  # reference on B (ties: B), incident A
        ref, face, inc, normals, offsets, a_incident = B, fb, A, nB, oB, True
    else:
        ref, face, inc, normals, offsets, a_incident = A, fa, B, nA, oA, False
    n, off = normals[face], offsets[face]
    inc_n = nA if a_incident else nB
    edge = int(np.argmin(inc_n @ n))
    p = [inc[edge], inc[(edge + 1) % len(inc)]]
    v1, v2 = ref[face], ref[(face + 1) % len(ref)]
    t = (v2 - v1) / np.hypot(*(v2 - v1))
    lo, hi = t @ v1 - margin, t @ v2 + margin
    points = []
    for end in range(2):  # clip the incident edge to [lo, hi] along the face
        q = p[end]
        tq, other = t @ q, p[1 - end]
        if tq < lo or tq > hi:
            to = t @ other
            if (tq < lo and to < lo) or (tq > hi and to > hi):
                return a_incident, face, edge, [], n
            bound = lo if tq < lo else hi
            q = q + (other - q) * (bound - tq) / (to - tq)
        gap = float(q @ n - off)
        if gap < margin:
            points.append((end, q, gap))
    return a_incident, face, edge, points, n


def pair_contacts(i: int, spec_i: ParcelSpec, y_i, j: int, spec_j: ParcelSpec, y_j, margin: float) -> list[Contact]:
    """Every contact between parcels ``i`` and ``j`` (their convex parts pairwise, :func:`convex_manifold`).

    Face normals make corner-on-corner meetings push along a face, never across it; a corner sliding past another
    meets the face's line, not the corner point, so it cannot slip inside between two steps.
    """
    out: list[Contact] = []
    parts_i, parts_j = _placed_parts(spec_i, y_i), _placed_parts(spec_j, y_j)
    for pa, (A, fa, ca, ra) in enumerate(parts_i):
        for pb, (B, fb, cb, rb) in enumerate(parts_j):
            if (ca[0] - cb[0]) ** 2 + (ca[1] - cb[1]) ** 2 > (ra + rb + margin) ** 2:
                continue
            m = convex_manifold(A, B, margin, fa, fb)
            if m is None:
                continue
            a_incident, face, edge, points, n = m
            owner, other = (i, j) if a_incident else (j, i)
            for end, q, gap in points:
                out.append(Contact(owner, other, (pa, pb, a_incident, face, edge, end), q, n, gap))
    return out


def _part_frames(spec: ParcelSpec) -> list[tuple]:
    """Each convex part in the body frame: vertices, (normals, offsets) of its faces, centre and radius."""
    frames = []
    for v in convex_parts(spec):
        n, o = _faces(v)
        c = v.mean(axis=0)
        frames.append((v, n, o, c, float(np.max(np.hypot(*(v - c).T)))))
    return frames


def _placed_parts(spec: ParcelSpec, pose):
    """Each convex part at ``pose``: world vertices, (normals, offsets) of its faces, centre and radius."""
    cache = spec.derived("part_frames", _part_frames, spec)
    cs, sn = np.cos(pose[2]), np.sin(pose[2])
    R = np.array([[cs, -sn], [sn, cs]])
    x = np.array([pose[0], pose[1]])
    out = []
    for v, n, o, c, r in cache:
        nw = n @ R.T
        out.append((v @ R.T + x, (nw, o + nw @ x), R @ c + x, r))
    return out


def place(v: np.ndarray, pose) -> np.ndarray:
    """Body-frame points ``v`` (k, 2) placed at ``pose`` = (x, y, theta, ...): world coordinates, m."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return np.column_stack([pose[0] + c * v[:, 0] - s * v[:, 1], pose[1] + s * v[:, 0] + c * v[:, 1]])


def point_reach(spec: ParcelSpec, y, window: float, *, law: FrictionLaw | str, mu_max: float, gravity: float,
                wheel_speed: float, speed_floor: float = 0.0) -> tuple[float, float]:
    """Upper bounds on how far (m) any point of the parcel can move in ``window`` s driven by the wheels alone, and
    on the speed (m/s) any point can reach in that time: the friction law's own bound
    (:meth:`~virtual_vehicle.physics.laws.base.FrictionLaw.reach`, ``law`` a law or its registered name) from
    ``S0 = |v| + |omega| R`` (R the footprint radius), ``rate = mu_max g (1 + m R^2 / I)`` and the parcel's lever
    ``1 + m R^2 / I`` (:func:`lever_of`). ``speed_floor`` raises S0 (m/s), e.g. to what a push from another parcel
    could give.

    >>> from virtual_vehicle.model.parcel import rectangle
    >>> point_reach(rectangle(0.2, 0.2, 1.0, 0.5), [0, 0, 0, 0.1, 0, 0], 1.0, law="coulomb", mu_max=0.0,
    ...             gravity=9.81, wheel_speed=0.0)
    (0.1, 0.1)
    """
    R = spec.radius
    s0 = max(float(np.hypot(y[3], y[4]) + abs(y[5]) * R), speed_floor)
    lever = lever_of(spec)
    dist, speed = _law(law).reach(s0, window, rate=mu_max * gravity * lever, wheel_speed=wheel_speed, lever=lever)
    return float(dist), float(speed)


def _law(law: FrictionLaw | str) -> FrictionLaw:
    """``law``, or the registered law of that name."""
    return law_named(law) if isinstance(law, str) else law


def lever_of(spec: ParcelSpec) -> float:
    """``1 + m R^2 / I`` of parcel ``spec``: how much faster its rim can speed up than its centre of mass."""
    return 1.0 + spec.mass * spec.radius * spec.radius / spec.inertia


def point_reaches(radius, lever, Y, window: float, *, law: FrictionLaw | str, mu_max, gravity: float,
                  wheel_speed: float, speed_floor=0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`point_reach` of many parcels, by the same operations elementwise (so the same numbers): ``radius``
    (m), ``lever`` (:func:`lever_of`), ``mu_max`` and ``speed_floor`` (m/s) one value each, ``Y`` (k, 6) their
    states."""
    Y = np.asarray(Y, dtype=float).reshape(-1, 6)
    s0 = np.maximum(np.hypot(Y[:, 3], Y[:, 4]) + np.abs(Y[:, 5]) * radius, speed_floor)
    lever = np.asarray(lever, dtype=float)
    rate = np.asarray(mu_max, dtype=float) * gravity * lever
    return _law(law).reach(s0, window, rate=rate, wheel_speed=wheel_speed, lever=lever)


def wheel_speed_of(velocities: np.ndarray) -> float:
    """The fastest contact surface speed (m/s) of ``velocities`` ((n, 2), m/s), 0 for none: what the reach bounds
    take as ``wheel_speed``."""
    return float(np.max(np.hypot(velocities[:, 0], velocities[:, 1]))) if len(velocities) else 0.0


def wheel_frame(velocities: np.ndarray) -> tuple[np.ndarray, float]:
    """A frame velocity (m/s, (2,)) near all of ``velocities`` ((n, 2), m/s) and the largest wheel speed relative
    to it (m/s): the middle of their bounding box when that is closer to them all than rest is, else rest and
    :func:`wheel_speed_of`. On a uniform field the frame is the field and the relative speed 0."""
    if not len(velocities):
        return np.zeros(2), 0.0
    centre = 0.5 * (velocities.min(axis=0) + velocities.max(axis=0))
    spread = float(np.max(np.hypot(velocities[:, 0] - centre[0], velocities[:, 1] - centre[1])))
    fastest = wheel_speed_of(velocities)
    return (centre, spread) if spread < fastest else (np.zeros(2), fastest)


def rigid_rotation(positions: np.ndarray, velocities: np.ndarray, directions: np.ndarray,
                   beyond: float = np.inf) -> tuple[np.ndarray, float, float] | None:
    """The rigid rotation of the plane nearest (least squares) the surface ``velocities`` ((n, 2), m/s) of entries
    at ``positions`` ((n, 2), m): its centre (m, (2,)) and angular speed (rad/s, counter-clockwise), with how far
    the wheels are from it (m/s): the largest, over the entries, of an entry's speed relative to it,
    ``|v - omega x (X - centre)|``, and of the sum of that along each of its wheels (``directions`` (n, k, 2) their
    unit drive directions, zero rows for absent wheels), ``sum_k |d_k . (v - omega x (X - centre))|``; 0 to
    rounding on a rotation field (:class:`~virtual_vehicle.model.fields.Rotation`, or a :class:`~virtual_vehicle.model.fields.Twist`
    that turns). None where there is no rotation (fewer than two entries, or omega 0 to rounding: a translation,
    which :func:`wheel_frame` takes), or where the wheels are ``beyond`` (m/s) or further off it: then the rotation
    is fitted to at most 64 entries spread over the array first, and a field whose sample is that far off it is
    given up without the whole array's pass (a sorter's field changes every tick)."""
    P = np.asarray(positions, dtype=float)
    V = np.asarray(velocities, dtype=float)
    D = np.asarray(directions, dtype=float)
    if len(P) < 2:
        return None
    stride = max(1, len(P) // 64)
    if np.isfinite(beyond) and stride > 1:
        sample = _rotation_fit(P[::stride], V[::stride], D[::stride])
        if sample is None or sample[2] >= beyond:  # the whole array is at least that far off the sample's frame
            return None
    found = _rotation_fit(P, V, D)
    return None if found is None or found[2] >= beyond else found


def _rotation_fit(P: np.ndarray, V: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """:func:`rigid_rotation` over all of the entries given."""
    p_mean, v_mean = P.mean(axis=0), V.mean(axis=0)
    dp, dv = P - p_mean, V - v_mean
    spread = float(np.sum(dp * dp))
    fastest = float(np.max(np.abs(V)))
    if spread == 0.0 or fastest == 0.0:
        return None
    omega = float(np.sum(dp[:, 0] * dv[:, 1] - dp[:, 1] * dv[:, 0])) / spread
    if abs(omega) * np.sqrt(spread / len(P)) <= 1e-12 * fastest:
        return None
    centre = p_mean + np.array([-v_mean[1], v_mean[0]]) / omega  # where v_mean + omega x (X - p_mean) is 0
    r = P - centre
    rel = V - omega * np.column_stack([-r[:, 1], r[:, 0]])
    along = np.sum(np.abs(np.einsum("ikj,ij->ik", D, rel)), axis=1)
    slack = float(np.max(np.maximum(along, np.hypot(rel[:, 0], rel[:, 1]))))
    return centre, omega, slack


def reach_bounds(s0: np.ndarray, lever_mu: np.ndarray, window: float, *, law: FrictionLaw | str, gravity: float,
                 wheel_speed: float, lever=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`point_reach` for many parcels at once: ``s0`` (m/s) their fastest point speeds now, ``lever_mu``
    their ``mu_max (1 + m R^2 / I)`` and ``lever`` their ``1 + m R^2 / I`` (None: the law's bound without it);
    returns the distance (m) and speed (m/s) bounds, arrays (the same formulas as :func:`point_reach`)."""
    s0 = np.asarray(s0, dtype=float)
    return _law(law).reach(s0, window, rate=np.asarray(lever_mu, dtype=float) * gravity, wheel_speed=wheel_speed,
                           lever=None if lever is None else np.asarray(lever, dtype=float))


def push_gain(spec: ParcelSpec) -> float:
    """How much faster than the contact point any point of the parcel can move after an inelastic push:
    ``1 + R / k`` with R the footprint radius and ``k = sqrt(I / m)`` the radius of gyration (a push at lever
    ``rho`` gives ``v = J/m``, ``omega = J rho / I``; the ratio of point speed to contact speed is below this)."""
    return 1.0 + spec.radius / np.sqrt(spec.inertia / spec.mass)


def overlap_area(spec_i: ParcelSpec, y_i, spec_j: ParcelSpec, y_j) -> float:
    """Area (m^2) common to two parcels' footprints at their poses; 0 when apart or touching along an edge."""
    return float(shapely.intersection(spec_i.world_polygon(y_i), spec_j.world_polygon(y_j)).area)


class Rows:
    """The rows of one step's complementarity problem over a group of bodies (velocity level, impulses in N s).

    Each row acts on body ``a`` through Jacobian ``Ja`` (3,) and, optionally, on body ``b`` through ``Jb``; its
    velocity is ``Ja nu_a + Jb nu_b`` (m/s). Kinds: a *box* row (a wheel: impulse in [lo, hi], driving the velocity
    toward ``target`` = the wheel speed), a *normal* row (impulse >= 0, velocity >= ``target``) and a *friction* row
    (impulse within +-``mu`` times its normal row's impulse, driving the velocity toward 0).
    """

    def __init__(self):
        self.a: list[int] = []
        self.b: list[int] = []
        self.Ja: list[tuple[float, float, float]] = []
        self.Jb: list[tuple[float, float, float]] = []
        self.target: list[float] = []
        self.lo: list[float] = []
        self.hi: list[float] = []
        self.normal_of: list[int] = []
        self.mu: list[float] = []
        self.warm: list[float] = []

    def __len__(self) -> int:
        return len(self.a)

    def _add(self, a, Ja, b, Jb, target, lo, hi, normal_of, mu, warm) -> int:
        self.a.append(a)
        self.Ja.append(tuple(map(float, Ja)))
        self.b.append(b)
        self.Jb.append((0.0, 0.0, 0.0) if Jb is None else tuple(map(float, Jb)))
        self.target.append(float(target))
        self.lo.append(float(lo))
        self.hi.append(float(hi))
        self.normal_of.append(normal_of)
        self.mu.append(float(mu))
        self.warm.append(float(warm))
        return len(self.a) - 1

    def box(self, body: int, J, target: float, bound: float, warm: float = 0.0) -> int:
        """A box row on body ``body`` (a wheel): Jacobian ``J`` (3,), driving its velocity toward ``target`` (m/s)
        with an impulse within +-``bound`` (N s), warm-started at ``warm``; returns its index."""
        return self._add(body, J, -1, None, target, -bound, bound, -1, 0.0, warm)

    def contact(self, ia: int, ib: int, c: Contact, ca, cb, h: float, params: ContactParams,
                warm=(0.0, 0.0)) -> tuple[int, int]:
        """A normal and a friction row for contact ``c`` between bodies ``ia`` (owner of the point, centre of mass
        ``ca``) and ``ib`` (centre ``cb``); returns their indices."""
        n = c.normal
        t = np.array([-n[1], n[0]])
        ra, rb = c.point - ca, c.point - cb
        depth = -c.gap
        target = -c.gap / h if c.gap >= 0 else (params.beta * (depth - params.slop) / h if depth > params.slop else 0.0)
        rows = []
        for d in (n, t):
            Ja = (d[0], d[1], ra[0] * d[1] - ra[1] * d[0])
            Jb = (-d[0], -d[1], -(rb[0] * d[1] - rb[1] * d[0]))
            rows.append((Ja, Jb))
        k = self._add(ia, rows[0][0], ib, rows[0][1], target, 0.0, np.inf, -1, 0.0, warm[0])
        f = self._add(ia, rows[1][0], ib, rows[1][1], 0.0, 0.0, 0.0, k, params.mu, warm[1])
        return k, f


def solve_rows(rows: Rows, nu: np.ndarray, minv: np.ndarray, max_sweeps: int, tol: float):
    """Projected Gauss-Seidel on ``rows`` for bodies with free twists ``nu`` (B, 3) and inverse masses ``minv``
    (B, 3) (1/kg, 1/kg, 1/(kg m^2)). Returns (impulses (m,), twists after the step (B, 3), sweeps, converged)."""
    V = [list(map(float, v)) for v in nu]
    M = [tuple(map(float, m)) for m in minv]
    lam = list(rows.warm)
    m = len(rows)
    a, b, Ja, Jb = rows.a, rows.b, rows.Ja, rows.Jb
    lo, hi, tgt, nof, mus = rows.lo, rows.hi, rows.target, rows.normal_of, rows.mu

    def apply(r, d):
        va, ma, ja = V[a[r]], M[a[r]], Ja[r]
        va[0] += ma[0] * ja[0] * d
        va[1] += ma[1] * ja[1] * d
        va[2] += ma[2] * ja[2] * d
        if b[r] >= 0:
            vb, mb, jb = V[b[r]], M[b[r]], Jb[r]
            vb[0] += mb[0] * jb[0] * d
            vb[1] += mb[1] * jb[1] * d
            vb[2] += mb[2] * jb[2] * d

    diag = []
    for r in range(m):
        ma, ja = M[a[r]], Ja[r]
        dg = ma[0] * ja[0] ** 2 + ma[1] * ja[1] ** 2 + ma[2] * ja[2] ** 2
        if b[r] >= 0:
            mb, jb = M[b[r]], Jb[r]
            dg += mb[0] * jb[0] ** 2 + mb[1] * jb[1] ** 2 + mb[2] * jb[2] ** 2
        diag.append(dg)
    for r in range(m):  # clamp the warm start into its bounds, then apply it
        if nof[r] >= 0:
            bound = mus[r] * max(lam[nof[r]], 0.0)
            lam[r] = min(max(lam[r], -bound), bound)
        else:
            lam[r] = min(max(lam[r], lo[r]), hi[r])
        if lam[r]:
            apply(r, lam[r])
    scale = 0.0
    for sweep in range(1, max_sweeps + 1):
        change = 0.0
        for r in range(m):
            if diag[r] == 0.0:
                continue
            va, ja = V[a[r]], Ja[r]
            vel = ja[0] * va[0] + ja[1] * va[1] + ja[2] * va[2]
            if b[r] >= 0:
                vb, jb = V[b[r]], Jb[r]
                vel += jb[0] * vb[0] + jb[1] * vb[1] + jb[2] * vb[2]
            new = lam[r] - (vel - tgt[r]) / diag[r]
            if nof[r] >= 0:
                bound = mus[r] * lam[nof[r]]
                new = -bound if new < -bound else bound if new > bound else new
            else:
                new = lo[r] if new < lo[r] else hi[r] if new > hi[r] else new
            d = new - lam[r]
            if d:
                lam[r] = new
                apply(r, d)
                change = max(change, abs(d))
        scale = max(scale, max((abs(v) for v in lam), default=0.0))
        if change <= tol * max(scale, 1e-300):
            return np.array(lam), np.array(V), sweep, True
    return np.array(lam), np.array(V), max_sweeps, False
