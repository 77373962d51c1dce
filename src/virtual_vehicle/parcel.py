"""Parcels: what they are (footprint, mass, inertia, friction) and where they are (planar state).

Units: m, kg, kg m^2, rad, m/s, rad/s. The footprint is a convex polygon given in the parcel's body frame, whose
origin is the centre of mass; the pose (x, y, theta) places that frame in the world.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import shapely
from shapely import affinity

from .errors import ScenarioError

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
                raise ScenarioError(f"parcels.{self.name}.{attr}", f"must be a positive number{' in ' + unit if unit else ''}, got {v}")
        if self.mu_static is not None and not (np.isfinite(self.mu_static) and self.mu_static >= self.mu):
            raise ScenarioError(f"parcels.{self.name}.mu_static",
                                f"must be at least the kinetic mu ({self.mu}), got {self.mu_static}")
        fp = np.array(self.footprint, dtype=float)
        if fp.ndim != 2 or fp.shape[1] != 2 or len(fp) < 3 or not np.all(np.isfinite(fp)):
            raise ScenarioError(f"parcels.{self.name}.footprint", "needs at least three finite [x, y] vertices")
        poly = shapely.Polygon(fp)
        if not poly.is_valid or poly.area <= 0:
            raise ScenarioError(f"parcels.{self.name}.footprint", "is not a simple polygon with positive area")
        if _signed_area(fp) < 0:
            fp = fp[::-1].copy()
        if not poly.contains(shapely.Point(0.0, 0.0)):
            raise ScenarioError(f"parcels.{self.name}.footprint", "the centre of mass (body origin) must lie inside the footprint")
        fp.setflags(write=False)
        object.__setattr__(self, "footprint", fp)

    @cached_property
    def polygon(self) -> shapely.Polygon:
        """The footprint as a shapely polygon in the body frame."""
        return shapely.Polygon(self.footprint)

    @cached_property
    def convex(self) -> bool:
        """Whether the footprint is convex (then margins use its half-planes, which is faster)."""
        return bool(np.isclose(self.polygon.convex_hull.area, self.polygon.area, rtol=1e-12))

    @cached_property
    def halfplanes(self) -> tuple[np.ndarray, np.ndarray]:
        """Outward unit normals (k, 2) and offsets (k,) of the footprint edges: inside iff normals @ p < offsets."""
        a = self.footprint
        b = np.roll(a, -1, axis=0)
        edge = b - a
        normals = np.column_stack([edge[:, 1], -edge[:, 0]])  # outward for a counter-clockwise polygon
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        offsets = np.einsum("ij,ij->i", normals, a)
        return normals, offsets

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
            raise ScenarioError(f"parcels.{name}.{attr}", f"must be a positive length in m, got {v}")
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
    c, s = np.cos(P[..., 2]), np.sin(P[..., 2])
    dx = pts[..., 0] - P[..., 0]
    dy = pts[..., 1] - P[..., 1]
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
        raise ScenarioError(f"parcels.{name}.vertices", "needs at least three finite [x, y] vertices in m")
    shape = shapely.Polygon(v)
    if not shape.is_valid or shape.area <= 0:
        raise ScenarioError(f"parcels.{name}.vertices", "is not a simple polygon with positive area (check the "
                            "vertex order and that edges do not cross)")
    c = np.array([shape.centroid.x, shape.centroid.y]) if com is None else np.asarray(com, dtype=float)
    if not shape.contains(shapely.Point(*c)):
        raise ScenarioError(f"parcels.{name}.com", f"the centre of mass {c.tolist()} must lie inside the outline")
    if not (np.isfinite(mass) and mass > 0):
        raise ScenarioError(f"parcels.{name}.mass", f"must be a positive number in kg, got {mass}")
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


def covered_pairs(specs: list[ParcelSpec], states, points: np.ndarray, tree) -> tuple[np.ndarray, np.ndarray]:
    """Every (parcel k, point j) with point j strictly under parcel k's footprint (margin > 0), for many parcels at
    once: ``states`` their poses (m, rad), ``points`` (n, 2) in m and ``tree`` a KD-tree over them. Returns the two
    index arrays, grouped by parcel in order.

    >>> import numpy as np
    >>> from scipy.spatial import cKDTree
    >>> pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.2, 0.0]])
    >>> k, j = covered_pairs([rectangle(0.3, 0.3, 1.0, 0.5)] * 2, [(0, 0, 0), (1, 0, 0)], pts, cKDTree(pts))
    >>> k.tolist(), j.tolist()
    ([0, 1], [0, 1])
    """
    if not len(specs):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    poses = np.array([np.asarray(y[:3], dtype=float) for y in states])
    reach = np.array([spec.radius for spec in specs]) * (1 + 1e-9) + 1e-12
    found = tree.query_ball_point(poses[:, :2], reach)
    counts = np.fromiter(map(len, found), dtype=int, count=len(found))
    point = np.fromiter(itertools.chain.from_iterable(found), dtype=int, count=int(counts.sum()))
    owner = np.repeat(np.arange(len(specs)), counts)
    keep = np.zeros(len(point), dtype=bool)
    shapes: dict[bytes, tuple[ParcelSpec, list[int]]] = {}
    for k, spec in enumerate(specs):  # margins depend on the outline only: one call per distinct outline
        shapes.setdefault(spec.footprint.tobytes(), (spec, []))[1].append(k)
    for spec, members in shapes.values():
        sel = slice(None) if len(shapes) == 1 else np.isin(owner, members)
        keep[sel] = pose_margins(spec, poses[owner[sel]], points[point[sel]]) > 0
    return owner[keep], point[keep]
