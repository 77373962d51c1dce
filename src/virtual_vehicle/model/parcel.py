"""Parcels: what they are (footprint, mass, inertia, friction) and where they are (planar state).

Units: m, kg, kg m^2, rad, m/s, rad/s. The footprint is a convex polygon given in the parcel's body frame, whose
origin is the centre of mass; the pose (x, y, theta) places that frame in the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import shapely
from numba import njit
from shapely import affinity


STATE_FIELDS = ("x", "y", "theta", "vx", "vy", "omega")
"""Order of the six planar state variables: position of the centre of mass (m), heading (rad), velocities (m/s,
rad/s)."""


@dataclass(frozen=True, eq=False)
class ParcelSpec:
    """An immutable description of a parcel.

    Attributes:
        footprint: (k, 2) vertices of a simple polygon (convex or not) in the body frame, whose origin is the
            centre of mass (which must lie inside), m; stored counter-clockwise.
        mass: kg.
        inertia: moment of inertia about the vertical axis through the centre of mass, kg m^2.
        mu: friction coefficient between the parcel's bottom and the rollers. Dimensionless for the Coulomb law;
            in s/m (force per unit normal force per unit slip speed) for the viscous law, as in the paper, which
            writes mu for both.
        name: label used in outputs.
        mu_static: static friction coefficient for the stick-slip law (default: ``mu``); at least ``mu``.
    """

    footprint: np.ndarray
    mass: float
    inertia: float
    mu: float
    name: str = "parcel"
    mu_static: float | None = None

    def __post_init__(self) -> None:
        for attr, unit in (("mass", "kg"), ("inertia", "kg m^2"), ("mu", "")):
            v = getattr(self, attr)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{attr} must be a positive number{' in ' + unit if unit else ''}, got {v}")
        if self.mu_static is not None and not (np.isfinite(self.mu_static) and self.mu_static >= self.mu):
            raise ValueError(f"mu_static must be at least the kinetic mu ({self.mu}), got {self.mu_static}")
        fp = np.array(self.footprint, dtype=float)
        if fp.ndim != 2 or fp.shape[1] != 2 or len(fp) < 3 or not np.all(np.isfinite(fp)):
            raise ValueError("the footprint needs at least three finite [x, y] vertices")
        poly = shapely.Polygon(fp)
        if not poly.is_valid or poly.area <= 0:
            raise ValueError("the footprint is not a simple polygon with positive area")
        if _signed_area(fp) < 0:
            fp = fp[::-1].copy()
        if not poly.contains(shapely.Point(0.0, 0.0)):
            raise ValueError("the centre of mass (body origin) must lie inside the footprint")
        fp.setflags(write=False)
        object.__setattr__(self, "footprint", fp)

    def derived(self, name: str, make, *args):
        """``make(*args)``, made once for this parcel and kept under ``name``: what the layers above work out from
        its outline (the convex parts parcel-parcel contact splits it into, say) is made once a parcel, not once a
        use. The description itself stays as it is (frozen); only this memo grows."""
        memo = self.__dict__.get("_derived")
        if memo is None:
            memo = self.__dict__["_derived"] = {}
        value = memo.get(name)
        if value is None:
            value = memo[name] = make(*args)
        return value

    @cached_property
    def polygon(self) -> shapely.Polygon:
        """The footprint as a shapely polygon in the body frame."""
        return shapely.Polygon(self.footprint)

    @cached_property
    def convex(self) -> bool:
        """Whether the footprint is convex (then margins use its half-planes, which is faster)."""
        return _outline_facts(self.outline_key)[0]

    @cached_property
    def halfplanes(self) -> tuple[np.ndarray, np.ndarray]:
        """Outward unit normals (k, 2) and offsets (k,) of the footprint edges: inside iff normals @ p < offsets.
        Worked out once per outline; each parcel keeps its own (writeable) copy, as the compiled engine has always
        been given them (a read-only array is another compiled signature, which a parcel of another kind then
        loads or compiles on its first use)."""
        normals, offsets = _outline_facts(self.outline_key)[1]
        return normals.copy(), offsets.copy()

    @cached_property
    def half_extents(self) -> tuple[float, float] | None:
        """(half length, half width) in m when the footprint is a rectangle centred on the centre of mass and aligned
        with the body axes (then margins have a closed form), else None."""
        fp = self.footprint
        hl, hw = np.max(np.abs(fp), axis=0)
        if len(fp) == 4 and np.allclose(np.abs(fp), [hl, hw], rtol=0, atol=1e-15 * max(hl, hw)):
            return float(hl), float(hw)
        return None

    @cached_property
    def outline_key(self) -> bytes:
        """The footprint's bytes: parcels with equal keys have the same outline (and the same margins)."""
        return self.footprint.tobytes()

    @cached_property
    def radius(self) -> float:
        """Largest distance from the centre of mass to the footprint, m."""
        return float(np.max(np.linalg.norm(self.footprint, axis=1)))

    def weight(self, gravity: float) -> float:
        """Weight in N for gravitational acceleration ``gravity`` (m/s^2)."""
        return self.mass * gravity

    def world_polygon(self, pose) -> shapely.Polygon:
        """The footprint placed at ``pose`` = (x, y, theta)."""
        x, y, th = pose[:3]
        return affinity.translate(affinity.rotate(self.polygon, th, origin=(0, 0), use_radians=True), x, y)


@lru_cache(maxsize=1024)
def _outline_facts(key: bytes) -> tuple[bool, tuple[np.ndarray, np.ndarray]]:
    """Whether the counter-clockwise footprint whose float64 (k, 2) vertices are the bytes ``key``
    (:attr:`ParcelSpec.outline_key`) is convex, and its edges' outward unit normals and offsets, read-only: worked
    out once per outline, not once per parcel (a run of 200 parcels of one size made them 200 times, a quarter of its
    set-up), for the last 1024 outlines asked for."""
    a = np.frombuffer(key, dtype=np.float64).reshape(-1, 2)
    polygon = shapely.Polygon(a)
    convex = bool(np.isclose(polygon.convex_hull.area, polygon.area, rtol=1e-12))
    edge = np.roll(a, -1, axis=0) - a
    normals = np.column_stack([edge[:, 1], -edge[:, 0]])  # outward for a counter-clockwise polygon
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = np.einsum("ij,ij->i", normals, a)
    normals.setflags(write=False)
    offsets.setflags(write=False)
    return convex, (normals, offsets)


def _signed_area(v: np.ndarray) -> float:
    x, y = v[:, 0], v[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def rectangle(length: float, width: float, mass: float, mu: float, inertia: float | None = None, name: str = "parcel",
              mu_static: float | None = None) -> ParcelSpec:
    """A rectangular parcel ``length`` (along body x) by ``width`` (m), centre of mass at its centre.

    ``inertia`` defaults to that of a uniform plate, ``mass * (length**2 + width**2) / 12`` (kg m^2).
    """
    for attr, v in (("length", length), ("width", width)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{attr} must be a positive length in m, got {v}")
    hl, hw = length / 2.0, width / 2.0
    fp = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
    if inertia is None:
        inertia = mass * (length**2 + width**2) / 12.0
    return ParcelSpec(fp, float(mass), float(inertia), float(mu), name, mu_static)


def footprint_margins(spec: ParcelSpec, pose, points: np.ndarray) -> np.ndarray:
    """Signed margin (m) of each point with respect to the footprint at ``pose`` = (x, y, theta, ...).

    Positive strictly inside (it is then the distance to the nearest edge), negative outside (for a convex footprint
    the most violated edge's distance, for a non-convex one the distance to the polygon). A cell supports the
    parcel iff its margin is positive; a support change is a zero crossing of some margin. ``pose`` may also be a
    (k, >=3) array of poses; the result is then (k, len(points)).
    """
    pose = np.asarray(pose, dtype=float)
    many = pose.ndim == 2
    P = np.atleast_2d(pose)
    pts = np.asarray(points, dtype=float)
    m = pose_margins(spec, P[:, None, :], pts[None])
    return m if many else m[0]


def pose_margins(spec: ParcelSpec, poses, points) -> np.ndarray:
    """Signed margins (m, as :func:`footprint_margins`) of ``points`` (..., 2) in the footprint at ``poses``
    (..., >=3), each point against its own pose (the two broadcast against each other)."""
    P = np.asarray(poses, dtype=float)
    pts = np.asarray(points, dtype=float)
    return _turned_margins(spec, np.cos(P[..., 2]), np.sin(P[..., 2]), pts[..., 0] - P[..., 0], pts[..., 1] - P[..., 1])


def _turned_margins(spec: ParcelSpec, c, s, dx, dy) -> np.ndarray:
    """:func:`pose_margins` of the points (dx, dy) (m) from the centre of mass, the parcel turned by the angle of
    cosine ``c`` and sine ``s``."""
    bx = c * dx + s * dy  # world -> body: rotate by -theta
    by = -s * dx + c * dy
    half = spec.half_extents
    if half is not None:  # rectangle: the minimum over its four half-planes in closed form
        return np.minimum(half[0] - np.abs(bx), half[1] - np.abs(by))
    if not spec.convex:  # signed Euclidean distance to the boundary: continuous, positive inside
        inside = shapely.contains_xy(spec.polygon, bx, by)
        dist = shapely.distance(spec.polygon.exterior, shapely.points(bx, by))
        return np.where(inside, dist, -dist)
    normals, offsets = spec.halfplanes
    return np.min(offsets - (bx[..., None] * normals[:, 0] + by[..., None] * normals[:, 1]), axis=-1)


def plate_inertia(vertices: np.ndarray, mass: float, about=(0.0, 0.0)) -> float:
    """Moment of inertia (kg m^2) about the vertical axis through ``about`` of a uniform plate of ``mass`` (kg)
    with outline ``vertices`` (m): the polygon second-moment formula, then the parallel-axis theorem."""
    v = np.asarray(vertices, dtype=float)
    x, y = v[:, 0], v[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2
    cx = ((x + xn) * cross).sum() / (6 * area)
    cy = ((y + yn) * cross).sum() / (6 * area)
    polar = ((x * x + x * xn + xn * xn + y * y + y * yn + yn * yn) * cross).sum() / 12  # about the origin
    i_centroid = mass * (polar / area - (cx * cx + cy * cy))
    return float(i_centroid + mass * ((cx - about[0]) ** 2 + (cy - about[1]) ** 2))


def polygon(vertices, mass: float, mu: float, com=None, inertia: float | None = None, name: str = "parcel",
            mu_static: float | None = None) -> ParcelSpec:
    """A parcel with any simple outline ``vertices`` ((k, 2), m, in any frame), convex or not.

    ``com`` (m, in that frame) is its centre of mass, by default the centroid of a uniform plate; the body frame is
    the vertices' frame moved to ``com``. ``inertia`` defaults to that of a uniform plate of the outline about
    ``com`` (parallel-axis theorem when ``com`` is not the centroid).

    >>> round(polygon([[0, 0], [2, 0], [2, 1], [0, 1]], 3.0, 0.5).inertia, 12)  # a 2 x 1 plate: m (4 + 1) / 12
    1.25
    """
    v = np.asarray(vertices, dtype=float)
    if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3 or not np.all(np.isfinite(v)):
        raise ValueError("vertices must be at least three finite [x, y] points in m")
    shape = shapely.Polygon(v)
    if not shape.is_valid or shape.area <= 0:
        raise ValueError("vertices do not outline a simple polygon with positive area (check the vertex order and "
                         "that edges do not cross)")
    c = np.array([shape.centroid.x, shape.centroid.y]) if com is None else np.asarray(com, dtype=float)
    if not shape.contains(shapely.Point(*c)):
        raise ValueError(f"com, the centre of mass {c.tolist()}, must lie inside the outline")
    if not (np.isfinite(mass) and mass > 0):
        raise ValueError(f"mass must be a positive number in kg, got {mass}")
    if inertia is None:
        inertia = plate_inertia(v, mass, about=c)
    return ParcelSpec(v - c, float(mass), float(inertia), float(mu), name, mu_static)


def supporting_cells(spec: ParcelSpec, pose, positions: np.ndarray, tree=None) -> np.ndarray:
    """Indices (sorted) of the cells strictly under the footprint at ``pose``.

    >>> import numpy as np
    >>> spec = rectangle(0.3, 0.3, 1.0, 0.5)
    >>> supporting_cells(spec, (0.0, 0.0, 0.0), np.array([[0.1, 0.1], [0.2, 0.0], [0.15, 0.0]])).tolist()
    [0]
    """
    positions = np.asarray(positions, dtype=float)
    if tree is not None:
        idx = np.asarray(sorted(tree.query_ball_point((float(pose[0]), float(pose[1])), spec.radius * (1 + 1e-9) + 1e-12)), dtype=int)
    else:
        idx = np.arange(len(positions))
    if len(idx) == 0:
        return idx
    m = footprint_margins(spec, pose, positions[idx])
    return idx[m > 0]


class PointGrid:
    """Fixed points (n, 2) (m) binned into square buckets, to gather every point near many centres at once.

    A KD-tree answers a many-centre radius query with one Python list per centre: for 200 parcels over the 5 x 10^4
    sensor points of a 100 x 100 hall that took ~2 ms, most of it making Python integers. Here the buckets are
    sorted row by row, so the buckets of one row of a centre's bounding box are one slice of the sorted points, and
    the gather is a few array operations. The bucket side is chosen for about ``per_bucket`` points a bucket (and
    never so small that a thin layout gets more than ~n / per_bucket buckets in a row), so memory is linear in n.

    >>> grid = PointGrid([[0.0, 0.0], [1.0, 0.0], [0.2, 0.0]])
    >>> owner, point = grid.near([[0.0, 0.0], [1.0, 0.0]], 0.25)
    >>> sorted(point[owner == 0].tolist()), point[owner == 1].tolist()
    ([0, 2], [1])
    """

    def __init__(self, points, per_bucket: float = 1.0):
        pts = np.array(points, dtype=float).reshape(-1, 2)  # its own, read-only: one compiled signature for all
        if not np.all(np.isfinite(pts)):
            raise ValueError("points must be finite")
        pts.setflags(write=False)
        self.points = pts
        n = len(pts)
        self.lo = pts.min(axis=0) if n else np.zeros(2)
        span = pts.max(axis=0) - self.lo if n else np.zeros(2)
        size = max(np.sqrt(per_bucket * span[0] * span[1] / max(n, 1)), per_bucket * float(span.max()) / max(n, 1))
        self.size = float(size) if size > 0 else 1.0
        bucket = np.floor((pts - self.lo) / self.size).astype(np.int64)
        self.shape = (int(bucket[:, 0].max()) + 1, int(bucket[:, 1].max()) + 1) if n else (1, 1)
        key = bucket[:, 1] * self.shape[0] + bucket[:, 0]
        self.order = np.argsort(key, kind="stable")  # the points, bucket by bucket, row by row
        self.start = np.searchsorted(key[self.order], np.arange(self.shape[0] * self.shape[1] + 1))

    def near(self, centres, reach) -> tuple[np.ndarray, np.ndarray]:
        """Every (centre k, point j) with point j in a bucket that meets the square of half side ``reach[k]`` (m, one
        value or one per centre) about centre k: all points within ``reach`` of it and some more. Returns the two
        index arrays, grouped by centre in order (within a centre, bucket row by bucket row). One compiled call: in
        array operations it took ~100 us whatever the number of centres, twice a tick for sensing and labels."""
        c = np.asarray(centres, dtype=float).reshape(-1, 2)
        r = np.broadcast_to(np.asarray(reach, dtype=float), (len(c),))
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r))):
            raise ValueError("centres and reach must be finite")
        return _near(self.order, self.start, self.lo[0], self.lo[1], self.size, self.shape[0], self.shape[1],
                     *(np.array(v, dtype=float) for v in (c[:, 0], c[:, 1], r)))  # fresh: one compiled signature

    def within(self, x: float, y: float, reach: float, present: np.ndarray | None = None) -> np.ndarray:
        """Indices (ascending) of the points within ``reach`` (m) of (``x``, ``y``) (m): ``|p - c|^2 <= reach^2``, as
        a KD-tree's ball query tests them; of those ``present`` ((n,) bool) only, when given. One compiled call over
        the buckets the square about the centre meets (a KD-tree query took ~15 us, a quarter of a quiet-step
        anchor; this takes ~2)."""
        x, y, reach = float(x), float(y), float(reach)
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(reach) and reach >= 0):
            raise ValueError(f"the centre must be finite and the reach finite and >= 0, got ({x}, {y}), {reach}")
        keep = ALL_PRESENT if present is None else present
        return _within(self.points, self.order, self.start, self.lo[0], self.lo[1], self.size, self.shape[0],
                       self.shape[1], keep, x, y, reach)


ALL_PRESENT = np.zeros(0, dtype=bool)
"""An empty ``present`` mask, as the compiled searches take it (:func:`_within` and the engine's loops): every cell
present."""


@njit(cache=True)
def _box(lo0, lo1, size, nx, ny, x, y, reach):
    """The bucket columns x0..x1 and rows y0..y1 that the square of half side ``reach`` (m) about (x, y) (m) meets,
    clipped to the grid of ``nx`` x ``ny`` buckets of side ``size`` from (lo0, lo1); no rows (y1 < y0) when it
    misses the grid."""
    # A hair wider than the square, so that a point on a bucket's edge a rounding step outside it is still tested
    # (its squared distance may round, or underflow, to within reach); floats: no integer overflow far off the grid.
    half = reach + 1e-9 * size
    first_x = np.floor((x - half - lo0) / size)
    last_x = np.floor((x + half - lo0) / size)
    first_y = np.floor((y - half - lo1) / size)
    last_y = np.floor((y + half - lo1) / size)
    if last_x < 0 or first_x > nx - 1 or last_y < 0 or first_y > ny - 1:
        return 0, -1, 0, -1
    # clipped as floats, then made integers
    return int(max(first_x, 0.0)), int(min(last_x, nx - 1.0)), int(max(first_y, 0.0)), int(min(last_y, ny - 1.0))


@njit(cache=True)
def _near(order, start, lo0, lo1, size, nx, ny, cx, cy, reach):
    """:meth:`PointGrid.near`, compiled: counts the pairs, then fills them."""
    total = 0
    boxes = np.empty((cx.shape[0], 4), np.int64)
    for k in range(cx.shape[0]):
        x0, x1, y0, y1 = _box(lo0, lo1, size, nx, ny, cx[k], cy[k], reach[k])
        boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = x0, x1, y0, y1
        for row in range(y0, y1 + 1):
            total += start[row * nx + x1 + 1] - start[row * nx + x0]
    owner = np.empty(total, np.int64)
    point = np.empty(total, np.int64)
    n = 0
    for k in range(cx.shape[0]):
        x0, x1, y0, y1 = boxes[k]
        for row in range(y0, y1 + 1):
            for j in range(start[row * nx + x0], start[row * nx + x1 + 1]):
                owner[n] = k
                point[n] = order[j]
                n += 1
    return owner, point


@njit(cache=True)
def _within(points, order, start, lo0, lo1, size, nx, ny, present, x, y, reach):
    """:meth:`PointGrid.within`, compiled; ``present`` empty for every point."""
    x0, x1, y0, y1 = _box(lo0, lo1, size, nx, ny, x, y, reach)
    count = 0
    for row in range(y0, y1 + 1):
        count += start[row * nx + x1 + 1] - start[row * nx + x0]
    out = np.empty(count, dtype=np.int64)
    n = 0
    r2 = reach * reach
    for row in range(y0, y1 + 1):
        for k in range(start[row * nx + x0], start[row * nx + x1 + 1]):
            j = order[k]
            dx, dy = points[j, 0] - x, points[j, 1] - y
            if dx * dx + dy * dy <= r2 and (present.shape[0] == 0 or present[j]):
                out[n] = j
                n += 1
    return np.sort(out[:n])


def covered_pairs(specs: list[ParcelSpec], states, grid: PointGrid) -> tuple[np.ndarray, np.ndarray]:
    """Every (parcel k, point j) with point j strictly under parcel k's footprint (margin > 0), for many parcels at
    once: ``states`` their poses (m, rad), ``grid`` a :class:`PointGrid` over the points. Returns the two index
    arrays, grouped by parcel in order.

    >>> pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.2, 0.0]])
    >>> k, j = covered_pairs([rectangle(0.3, 0.3, 1.0, 0.5)] * 2, [(0, 0, 0), (1, 0, 0)], PointGrid(pts))
    >>> k.tolist(), j.tolist()
    ([0, 1], [0, 1])
    """
    if not len(specs):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    try:  # states of one length (a plant's): one array, then its first three columns
        poses = np.array(states, dtype=float)[:, :3]
    except ValueError:
        poses = np.array([y[:3] for y in states], dtype=float)
    reach = np.array([spec.radius for spec in specs]) * (1 + 1e-9) + 1e-12  # the same floats as one by one
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(reach))):
        raise ValueError("poses must be finite")
    cos, sin = np.cos(poses[:, 2]), np.sin(poses[:, 2])  # once a parcel, not once a point (numpy's, as ever)
    shapes: dict[bytes, int] = {}  # margins depend on the outline only: each distinct outline once
    shape_of = np.array([shapes.setdefault(spec.outline_key, len(shapes)) for spec in specs], dtype=np.int64)
    first = np.unique(shape_of, return_index=True)[1]
    kinds, half, normals, offsets, counts = _outline_table([specs[k] for k in first.tolist()])
    owner, point, pending = _covered(grid.points, grid.order, grid.start, grid.lo[0], grid.lo[1], grid.size,
                                     grid.shape[0], grid.shape[1], np.ascontiguousarray(poses[:, 0]),
                                     np.ascontiguousarray(poses[:, 1]), reach, cos, sin, shape_of, kinds, half,
                                     normals, offsets, counts)
    if not pending.any():
        return owner, point
    keep = ~pending  # the pairs of non-convex outlines: shapely's signed distance decides them
    for s in np.flatnonzero(kinds == _POLYGON).tolist():
        sel = pending & (shape_of[owner] == s)
        mine, at = owner[sel], grid.points[point[sel]]
        dx, dy = at[:, 0] - poses[mine, 0], at[:, 1] - poses[mine, 1]
        keep[sel] = _turned_margins(specs[first[s]], cos[mine], sin[mine], dx, dy) > 0
    return owner[keep], point[keep]


_RECTANGLE, _CONVEX, _POLYGON = 0, 1, 2
"""Outline kinds of :func:`_covered`: margins in closed form, by half-planes, or left to shapely."""


def _outline_table(outlines: list[ParcelSpec]) -> tuple[np.ndarray, ...]:
    """What :func:`_covered` takes of each distinct outline: its kind, a rectangle's half extents (m), a convex
    outline's half-planes (normals and offsets, m; padded to the longest) and their number."""
    kinds = np.empty(len(outlines), dtype=np.int64)
    half = np.zeros((len(outlines), 2))
    most = max((len(spec.footprint) for spec in outlines if spec.half_extents is None and spec.convex), default=0)
    normals = np.zeros((len(outlines), most, 2))
    offsets = np.zeros((len(outlines), most))
    counts = np.zeros(len(outlines), dtype=np.int64)
    for s, spec in enumerate(outlines):
        if spec.half_extents is not None:
            kinds[s] = _RECTANGLE
            half[s] = spec.half_extents
        elif spec.convex:
            kinds[s] = _CONVEX
            n, b = spec.halfplanes
            normals[s, :len(b)], offsets[s, :len(b)], counts[s] = n, b, len(b)
        else:
            kinds[s] = _POLYGON
    return kinds, half, normals, offsets, counts


@njit(cache=True)
def _covered(points, order, start, lo0, lo1, size, nx, ny, cx, cy, reach, cos, sin, shape_of, kinds, half, normals,
             offsets, counts):
    """:func:`covered_pairs`, compiled: the pairs :meth:`PointGrid.near` finds, kept where the margin is positive,
    computed as :func:`_turned_margins` computes it (the same operations in the same order: the same floats), and
    those of non-convex outlines kept as pending (``pending`` True) for shapely to decide. (In array operations
    this took ~0.35 ms a tick for 200 parcels, twice: sensors and labels.)"""
    owner, point = _near(order, start, lo0, lo1, size, nx, ny, cx, cy, reach)
    pending = np.zeros(owner.shape[0], np.bool_)
    n = 0
    for q in range(owner.shape[0]):
        k, j = owner[q], point[q]
        s = shape_of[k]
        if kinds[s] == _POLYGON:
            pending[n] = True
        elif not _turned_margin(kinds[s], half[s], normals[s], offsets[s], counts[s], cos[k], sin[k],
                                points[j, 0] - cx[k], points[j, 1] - cy[k]) > 0:
            continue
        owner[n], point[n] = k, j
        n += 1
    return owner[:n], point[:n], pending[:n]


@njit(cache=True, inline="always")
def _turned_margin(kind, half, normals, offsets, count, c, sn, dx, dy):
    """:func:`_turned_margins` of one point (dx, dy) (m) for a rectangle (``half``) or a convex outline (``count``
    half-planes), compiled: the same operations in the same order, so the same float."""
    bx = c * dx + sn * dy  # world -> body: rotate by -theta
    by = -sn * dx + c * dy
    if kind == _RECTANGLE:
        return min(half[0] - abs(bx), half[1] - abs(by))
    margin = np.inf
    for e in range(count):
        margin = min(margin, offsets[e] - (bx * normals[e, 0] + by * normals[e, 1]))
    return margin
