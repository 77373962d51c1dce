"""Cell arrays: where the cells are and in which directions their two roller wheels drive.

Units: metres for positions; drive directions are unit vectors (dimensionless).

Each cell carries two motorised roller wheels with orthogonal drive directions (paper Section 2.1). A wheel pushes
the parcel along its drive direction and lets it slide freely along its axle. The paper lumps both wheels of a cell
at the cell centre, which is the model used here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .errors import ScenarioError

_COLLINEAR_TOL = 1e-9  # m: largest distance of a cell from the best-fit line for a layout to count as a row


@dataclass(frozen=True, eq=False)
class CellArray:
    """An immutable array of cells.

    Attributes:
        positions: (n, 2) cell centres, m.
        drive_directions: (n, 2, 2) unit drive direction of wheel k of cell i as ``drive_directions[i, k]``.
        pitch: nominal spacing between neighbouring cells, m (used for plots and search radii).
    """

    positions: np.ndarray
    drive_directions: np.ndarray
    pitch: float
    shape: tuple[int, ...] | None = field(default=None)
    wheel_active: np.ndarray | None = field(default=None)
    cell_of: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        pos = np.array(self.positions, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2 or len(pos) == 0:
            raise ScenarioError("array.points", f"cell positions must be a non-empty (n, 2) array, got {pos.shape}")
        if not np.all(np.isfinite(pos)):
            raise ScenarioError("array.points", "cell positions must be finite numbers")
        dirs = np.array(self.drive_directions, dtype=float)
        if dirs.shape != (len(pos), 2, 2):
            raise ScenarioError("array.drive_angle", f"drive directions must have shape ({len(pos)}, 2, 2)")
        norms = np.linalg.norm(dirs, axis=2)
        if not np.allclose(norms, 1.0, atol=1e-9):
            raise ScenarioError("array.drive_angle", "wheel drive directions must be unit vectors")
        if not np.allclose(np.einsum("ij,ij->i", dirs[:, 0], dirs[:, 1]), 0.0, atol=1e-9):
            raise ScenarioError("array.drive_angle", "the two wheels of a cell must drive in orthogonal directions")
        if cKDTree(pos).query_pairs(1e-9 * max(1.0, float(np.ptp(pos)))):
            raise ScenarioError("array.points", "two cells share the same position")
        if not (np.isfinite(self.pitch) and self.pitch > 0):
            raise ScenarioError("array.pitch", f"pitch must be a positive length in m, got {self.pitch}")
        active = np.ones((len(pos), 2), bool) if self.wheel_active is None else np.asarray(self.wheel_active, bool)
        cell_of = np.arange(len(pos)) if self.cell_of is None else np.asarray(self.cell_of, dtype=np.int64)
        for arr in (pos, dirs, active, cell_of):
            arr.setflags(write=False)
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "drive_directions", dirs)
        object.__setattr__(self, "wheel_active", active)
        object.__setattr__(self, "cell_of", cell_of)

    @cached_property
    def active_directions(self) -> np.ndarray:
        """(n, 2, 2) drive directions with those of absent wheels set to zero (what friction laws use)."""
        return self.drive_directions * self.wheel_active[:, :, None]

    @property
    def separate(self) -> bool:
        """True for a contact layer made by :func:`separate_wheels` (one wheel per contact point)."""
        return not bool(self.wheel_active.all())

    def contact_velocities(self, cell_velocities: np.ndarray) -> np.ndarray:
        """Surface velocities (m/s) of this layer's contacts from those of the cells they belong to: each present
        wheel keeps its own component."""
        V = np.asarray(cell_velocities, dtype=float)[self.cell_of]
        U = self.active_directions
        return np.einsum("ik,ikj->ij", np.einsum("ij,ikj->ik", V, U), U)

    @property
    def n(self) -> int:
        """Number of cells."""
        return len(self.positions)

    @cached_property
    def tree(self) -> cKDTree:
        """KD-tree over the cell centres, for radius queries."""
        return cKDTree(self.positions)

    @cached_property
    def is_line(self) -> bool:
        """True when all cells lie on one straight line (the paper's 1-D array). A parcel on such an array is
        assumed held laterally (the 1-D model: vertical force and one moment equation only)."""
        return _collinear(self.positions)

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the cell centres, m."""
        lo = self.positions.min(axis=0)
        hi = self.positions.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _collinear(points: np.ndarray, tol: float = _COLLINEAR_TOL) -> bool:
    """True if the points lie within ``tol`` metres of one straight line (or are a single point)."""
    if len(points) < 3:
        return True
    centred = points - points.mean(axis=0)
    # The smallest singular value / sqrt(n) is the RMS distance from the best-fit line.
    s = np.linalg.svd(centred, compute_uv=False)
    return bool(s[-1] <= tol * np.sqrt(len(points)))


def _drive_directions(n: int, drive_angle: float) -> np.ndarray:
    c, s = np.cos(drive_angle), np.sin(drive_angle)
    one = np.array([[c, s], [-s, c]])
    return np.broadcast_to(one, (n, 2, 2)).copy()


def grid(nx: int, ny: int, pitch: float, origin: tuple[float, float] = (0.0, 0.0), drive_angle: float = 0.0) -> CellArray:
    """A rectangular grid of ``nx`` columns by ``ny`` rows at spacing ``pitch`` (m), first cell at ``origin`` (m).

    Cells are numbered row by row: cell ``j * nx + i`` is column i, row j. Wheel 0 drives along ``drive_angle``
    (rad, from +x), wheel 1 at +90 degrees from it.

    >>> grid(2, 2, 0.1).positions.tolist()
    [[0.0, 0.0], [0.1, 0.0], [0.0, 0.1], [0.1, 0.1]]
    """
    if nx < 1 or ny < 1:
        raise ScenarioError("array.nx", f"a grid needs at least one column and one row, got {nx} x {ny}")
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny))
    pos = np.column_stack([ii.ravel() * pitch, jj.ravel() * pitch]) + np.asarray(origin, dtype=float)
    return CellArray(pos, _drive_directions(len(pos), drive_angle), float(pitch), shape=(ny, nx))


def row(n: int, pitch: float, origin: tuple[float, float] = (0.0, 0.0), drive_angle: float = 0.0) -> CellArray:
    """A single row of ``n`` cells along +x at spacing ``pitch`` (m): the paper's 1-D array."""
    if n < 1:
        raise ScenarioError("array.n", f"a row needs at least one cell, got {n}")
    return grid(n, 1, pitch, origin, drive_angle)


def from_points(points, pitch: float | None = None, drive_angle: float = 0.0) -> CellArray:
    """Cells at arbitrary ``points`` ((n, 2), m). ``pitch`` defaults to the median nearest-neighbour distance."""
    pos = np.asarray(points, dtype=float)
    if pos.ndim != 2 or pos.shape[-1] != 2 or len(pos) == 0:
        raise ScenarioError("array.points", f"points must be a non-empty list of [x, y] pairs, got shape {pos.shape}")
    if pitch is None:
        if len(pos) == 1:
            pitch = 1.0
        else:
            d, _ = cKDTree(pos).query(pos, k=2)
            pitch = float(np.median(d[:, 1]))
    return CellArray(pos, _drive_directions(len(pos), drive_angle), float(pitch))


def separate_wheels(cells: CellArray, offsets=None) -> CellArray:
    """The contact layer in which each of a cell's two wheels is its own support at its own offset (m, in the
    cell's frame, one row per wheel; default wheel 0 at (0, -pitch/4) and wheel 1 at (-pitch/4, 0)), pushing only
    along its own drive direction. The paper lumps both wheels at the cell centre (the default layer); here each
    wheel carries its own share of the load. Contact 2 i + k is wheel k of cell i.
    """
    q = cells.pitch / 4
    off = np.array([[0.0, -q], [-q, 0.0]]) if offsets is None else np.asarray(offsets, dtype=float)
    if off.shape != (2, 2) or not np.all(np.isfinite(off)):
        raise ScenarioError("array.wheel_offsets", "needs two finite [x, y] offsets in m, one per wheel")
    if np.allclose(off[0], off[1]):
        raise ScenarioError("array.wheel_offsets", "the two wheels of a cell must sit at different points")
    U = cells.drive_directions
    pos = cells.positions[:, None, :] + off[None, :, 0, None] * U[:, None, 0, :] + off[None, :, 1, None] * U[:, None, 1, :]
    dirs = np.empty((cells.n, 2, 2, 2))
    for k in range(2):
        u = U[:, k]
        dirs[:, k, 0] = u
        dirs[:, k, 1] = np.column_stack([-u[:, 1], u[:, 0]])
    active = np.tile([True, False], (2 * cells.n, 1))
    return CellArray(pos.reshape(-1, 2), dirs.reshape(-1, 2, 2), cells.pitch, None, active,
                     np.repeat(np.arange(cells.n), 2))
