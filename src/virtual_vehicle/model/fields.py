"""Wheel-velocity fields: the surface velocity (m/s) each cell's wheels give, as constant fields (paper 4: "each of
the cells is assumed to be spinning at a constant speed").

A field maps a :class:`~virtual_vehicle.model.layout.CellArray` to an (n, 2) array of cell velocities in m/s; the
component of a cell's velocity along each wheel's drive direction is that wheel's surface speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virtual_vehicle.model.layout import CellArray


@dataclass(frozen=True)
class Uniform:
    """Every cell drives at the same ``velocity`` (m/s)."""

    velocity: tuple[float, float]

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        return np.tile(np.asarray(self.velocity, dtype=float), (cells.n, 1))


@dataclass(frozen=True)
class Inward:
    """Each wheel spins toward ``center`` (m) at ``speed`` (m/s): per axis ``speed * sign(center - X_i)``, the
    paper's 2x2 inward field (eq. 21) on any array. A cell level with the centre along an axis leaves that wheel
    stopped."""

    center: tuple[float, float]
    speed: float

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        return self.speed * np.sign(np.asarray(self.center, dtype=float) - cells.positions)


@dataclass(frozen=True)
class ReversedEnd:
    """All cells drive at ``velocity`` (m/s) except the cells at the far end along it, which drive the opposite way:
    the 1-D oscillator of the authors' earlier paper (Section 3), and its 2-D version on a grid ("the last column").
    """

    velocity: tuple[float, float]

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        v = np.asarray(self.velocity, dtype=float)
        speed = float(np.linalg.norm(v))
        if speed == 0:
            raise ValueError("a reversed-end field needs a non-zero velocity")
        along = cells.positions @ (v / speed)
        end = along >= along.max() - 1e-9 * max(1.0, cells.pitch)
        out = np.tile(v, (cells.n, 1))
        out[end] = -v
        return out


@dataclass(frozen=True)
class PerCell:
    """Explicit velocities (m/s), one [vx, vy] per cell in the array's order."""

    values: tuple[tuple[float, float], ...]

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        v = np.asarray(self.values, dtype=float)
        if v.shape != (cells.n, 2):
            raise ValueError(f"a per-cell field needs one [vx, vy] per cell: {cells.n} rows, got shape {v.shape}")
        return v


@dataclass(frozen=True)
class Radial:
    """Every cell drives straight toward ``center`` (m) at ``speed`` (m/s) (away from it when ``speed`` < 0); a cell
    at the centre stops. Unlike :class:`Inward` (per-axis signs, the paper's eq. 21) the velocity points at the
    centre."""

    center: tuple[float, float]
    speed: float

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        d = np.asarray(self.center, dtype=float) - cells.positions
        r = np.hypot(d[:, 0], d[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where((r > 0)[:, None], self.speed * d / r[:, None], 0.0)


@dataclass(frozen=True)
class Squeeze:
    """Cells on either side of the line through ``point`` (m) along ``direction`` drive toward it at ``speed`` (m/s),
    and every cell also moves along the line at ``along`` (m/s): parcels gather onto the line (a singulator).
    Cells on the line drive only along it."""

    point: tuple[float, float]
    direction: tuple[float, float]
    speed: float
    along: float = 0.0

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        d = np.asarray(self.direction, dtype=float)
        norm = float(np.hypot(*d))
        if norm == 0:
            raise ValueError("a squeeze field needs a non-zero line direction")
        d = d / norm
        n = np.array([-d[1], d[0]])
        side = np.sign((cells.positions - np.asarray(self.point, dtype=float)) @ n)
        return -self.speed * side[:, None] * n + self.along * d


@dataclass(frozen=True)
class Rotation:
    """The velocity of a rigid rotation at ``omega`` (rad/s, counter-clockwise) about ``center`` (m):
    ``omega x (X_i - center)``."""

    center: tuple[float, float]
    omega: float

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        r = cells.positions - np.asarray(self.center, dtype=float)
        return self.omega * np.column_stack([-r[:, 1], r[:, 0]])


@dataclass(frozen=True)
class Twist:
    """The rigid-body velocity field of a parcel asked to move with twist (``vx``, ``vy`` m/s, ``omega`` rad/s)
    about the point ``center`` (m): ``v + omega x (X_i - center)``. Under the viscous and stick-slip laws a parcel
    at rest relative to these wheels feels no force, so it rides on them with exactly this twist."""

    center: tuple[float, float]
    twist: tuple[float, float, float]

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        vx, vy, w = (float(v) for v in self.twist)
        r = cells.positions - np.asarray(self.center, dtype=float)
        return np.column_stack([vx - w * r[:, 1], vy + w * r[:, 0]])


@dataclass(frozen=True)
class Regions:
    """Fields composed by region: each ``(outline, field)`` pair drives the cells inside its polygon ``outline``
    ((k, 2) m); the first region containing a cell wins; cells in no region follow ``default`` (stopped when None).
    Different parcels can so be given different fields."""

    regions: tuple
    default: object = None

    def velocities(self, cells: CellArray) -> np.ndarray:
        """(n, 2) surface velocity of every cell of ``cells`` under this field, m/s (world frame)."""
        import shapely

        out = np.zeros((cells.n, 2)) if self.default is None else self.default.velocities(cells)
        taken = np.zeros(cells.n, dtype=bool)
        for k, (outline, field) in enumerate(self.regions):
            poly = shapely.Polygon(np.asarray(outline, dtype=float))
            if not poly.is_valid or poly.area <= 0:
                raise ValueError(f"the outline of region {k} is not a simple polygon with positive area")
            inside = shapely.covers(poly, shapely.points(cells.positions)) & ~taken  # boundary cells included
            out[inside] = field.velocities(cells)[inside]
            taken |= inside
        return out


def limited(velocities: np.ndarray, drive_directions: np.ndarray, vmax: float) -> np.ndarray:
    """Cell velocities (n, 2) m/s with every wheel's surface speed clipped to ``vmax`` (m/s)."""
    speeds = np.clip(np.einsum("ij,ikj->ik", velocities, drive_directions), -vmax, vmax)
    return np.einsum("ik,ikj->ij", speeds, drive_directions)
