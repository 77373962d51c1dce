"""Cell arrays: where the cells are and in which directions their wheels drive.

Units: metres for positions, m/s for speeds; drive directions are unit vectors (dimensionless).

Each cell carries two motorised roller wheels with orthogonal drive directions (paper Section 2.1). A wheel pushes
the parcel along its drive direction and lets it slide freely along its axle. The paper lumps both wheels of a cell
at the cell centre, which is the default model here.

Two layers describe an array. The *cell layer* has one entry per controller: its position, its command frame (the
two orthogonal axes its wheel-speed command is given in, ``drive_directions``) and its network ports. The *contact
layer* has one entry per point where the parcel rests on the array, each belonging to a cell (``cell_of``) and
pushing along up to two of that cell's wheel directions. For the paper's lumped cells both layers are the same.
Other layers: :func:`separate_wheels` (each of the two wheels its own contact), :func:`three_wheels` (hexagonal
cells with three omni wheels at 120 degrees, as commercial omni-wheel conveyors use) and :func:`with_belts` (plain
conveyor belts, each one long cell with one drive direction, feeding or leaving the array).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from virtual_vehicle.model.parcel import PointGrid

COLLINEAR_TOL = 1e-9
"""m: the largest distance of a point from the best-fit line for points to count as collinear (a layout as a row)."""


@dataclass(frozen=True, eq=False)
class CellArray:
    """An immutable array of cells.

    Attributes:
        positions: (n, 2) cell centres, m.
        drive_directions: (n, 2, 2) unit drive direction of wheel k of cell i as ``drive_directions[i, k]``.
        pitch: nominal spacing between neighbouring cells, m (used for plots and search radii).
        shape: (rows, columns) of a rectangular grid, else None.
        wheel_active: (n, 2) False where an entry has no wheel along that drive direction (contact layers).
        cell_of: (n,) the cell (controller) each entry belongs to; ``arange(n)`` on a cell layer.
        wheel_of: (n, 2) which of its cell's physical wheels drives along each direction, -1 for none.
        ports: (n,) network ports of each cell: 4 on a square lattice, 6 on a hexagonal one, 0 for a plain conveyor
            belt (no controller, no messages).
        belt_speed: (n,) surface speed of a plain conveyor belt along its wheel-0 direction (m/s), NaN for cells that
            take commands.
    """

    positions: np.ndarray
    drive_directions: np.ndarray
    pitch: float
    shape: tuple[int, ...] | None = field(default=None)
    wheel_active: np.ndarray | None = field(default=None)
    cell_of: np.ndarray | None = field(default=None)
    wheel_of: np.ndarray | None = field(default=None)
    ports: np.ndarray | None = field(default=None)
    belt_speed: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        pos = np.array(self.positions, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2 or len(pos) == 0:
            raise ValueError(f"cell positions must be a non-empty (n, 2) array, got {pos.shape}")
        if not np.all(np.isfinite(pos)):
            raise ValueError("cell positions must be finite numbers")
        dirs = np.array(self.drive_directions, dtype=float)
        if dirs.shape != (len(pos), 2, 2):
            raise ValueError(f"drive directions must have shape ({len(pos)}, 2, 2)")
        norms = np.linalg.norm(dirs, axis=2)
        if not np.allclose(norms, 1.0, atol=1e-9):
            raise ValueError("wheel drive directions must be unit vectors")
        if not np.allclose(np.einsum("ij,ij->i", dirs[:, 0], dirs[:, 1]), 0.0, atol=1e-9):
            raise ValueError("the two wheels of a cell must drive in orthogonal directions")
        if cKDTree(pos).query_pairs(1e-9 * max(1.0, float(np.ptp(pos)))):
            raise ValueError("two cells share the same position")
        if not (np.isfinite(self.pitch) and self.pitch > 0):
            raise ValueError(f"pitch must be a positive length in m, got {self.pitch}")
        n = len(pos)
        active = np.ones((n, 2), bool) if self.wheel_active is None else np.asarray(self.wheel_active, bool)
        cell_of = np.arange(n) if self.cell_of is None else np.asarray(self.cell_of, dtype=np.int64)
        wheel_of = (np.tile([0, 1], (n, 1)) if self.wheel_of is None else np.asarray(self.wheel_of, dtype=np.int64))
        ports = np.full(n, 4, dtype=np.int64) if self.ports is None else np.asarray(self.ports, dtype=np.int64)
        belt = np.full(n, np.nan) if self.belt_speed is None else np.asarray(self.belt_speed, dtype=float)
        if active.shape != (n, 2) or cell_of.shape != (n,) or wheel_of.shape != (n, 2) or ports.shape != (n,) \
                or belt.shape != (n,):
            raise ValueError("wheel_active, wheel_of: (n, 2); cell_of, ports, belt_speed: (n,)")
        for name, arr in (("positions", pos), ("drive_directions", dirs), ("wheel_active", active),
                          ("cell_of", cell_of), ("wheel_of", wheel_of), ("ports", ports), ("belt_speed", belt)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @cached_property
    def active_directions(self) -> np.ndarray:
        """(n, 2, 2) drive directions with those of absent wheels set to zero (what friction laws use)."""
        return self.drive_directions * self.wheel_active[:, :, None]

    @cached_property
    def _direction_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """The directions of every cell's wheel 0 and of its wheel 1, each (n, 2) and contiguous."""
        return tuple(np.ascontiguousarray(self.drive_directions[:, k]) for k in range(2))

    def surface_velocities(self, wheel_speeds: np.ndarray) -> np.ndarray:
        """(n, 2) surface velocities (m/s) of the cells whose two wheels turn at ``wheel_speeds`` ((n, 2), m/s along
        their drive directions): each wheel's speed times its direction, summed. (From contiguous copies of the
        directions: twice as fast on 10^4 cells as from strided views, and a networked run does it every tick.)"""
        u0, u1 = self._direction_columns
        return wheel_speeds[:, 0:1] * u0 + wheel_speeds[:, 1:2] * u1

    @property
    def belts(self) -> np.ndarray:
        """(n,) True for plain conveyor belts (no controller; they run at ``belt_speed``)."""
        return np.isfinite(self.belt_speed)

    def belt_commands(self, wheel_speeds: np.ndarray) -> np.ndarray:
        """``wheel_speeds`` ((n, 2) m/s along each cell's drive directions) with the belts at their own speed: a belt
        runs along its length and cannot move its surface sideways."""
        belt = self.belts
        if not belt.any():
            return wheel_speeds
        out = np.array(wheel_speeds, dtype=float)
        out[belt, 0] = self.belt_speed[belt]
        out[belt, 1] = 0.0
        return out

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
    def grid(self) -> PointGrid:
        """The cell centres in buckets, for gathering the cells near many parcels at once."""
        return PointGrid(self.positions)

    @cached_property
    def is_line(self) -> bool:
        """True when all cells lie on one straight line (the paper's 1-D array). A parcel on such an array is
        assumed held laterally (the 1-D model: vertical force and one moment equation only)."""
        return collinear(self.positions)

    @cached_property
    def extent(self) -> float:
        """The largest |coordinate| of any cell centre, m: the scale of rounding noise in positions."""
        return float(np.max(np.abs(self.positions)))

    @cached_property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the cell centres, m."""
        lo = self.positions.min(axis=0)
        hi = self.positions.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def collinear(points: np.ndarray, tol: float = COLLINEAR_TOL) -> bool:
    """True if the points ((n, 2), m) lie within ``tol`` metres of one straight line (or are a single point): the
    test of a 1-D array and of a collinear contact set (the 1-D model of the normal forces)."""
    return bool(_collinear_kernel(np.ascontiguousarray(points, dtype=np.float64), tol))


@njit(cache=True)
def _collinear_kernel(points, tol):
    """:func:`collinear` compiled, for float64 points, without an SVD (LAPACK's took ~10-25 us on the ~12 points of
    a support set, and every new support pattern asks): the RMS distance of the centred points from the best-fit line
    is that of their components across its direction, the principal axis of their 2 x 2 scatter matrix. The axis is
    found to rounding (~1e-16 rad), so the distances are too; the square root of the matrix's smaller eigenvalue (the
    smallest singular value) would lose them to cancellation far above ``tol``."""
    n = points.shape[0]
    if n < 3:
        return True
    centred = np.empty((n, 2))
    for j in range(2):
        centred[:, j] = points[:, j] - points[:, j].mean()
    sxx = syy = sxy = 0.0
    for i in range(n):
        sxx += centred[i, 0] * centred[i, 0]
        syy += centred[i, 1] * centred[i, 1]
        sxy += centred[i, 0] * centred[i, 1]
    phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # the best-fit line's direction
    c, s = math.cos(phi), math.sin(phi)
    across = 0.0
    for i in range(n):
        d = c * centred[i, 1] - s * centred[i, 0]
        across += d * d
    return math.sqrt(across) <= tol * math.sqrt(n)  # sqrt(sum d^2) is the smallest singular value


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
        raise ValueError(f"a grid needs at least one column and one row (nx, ny >= 1), got {nx} x {ny}")
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny))
    pos = np.column_stack([ii.ravel() * pitch, jj.ravel() * pitch]) + np.asarray(origin, dtype=float)
    return CellArray(pos, _drive_directions(len(pos), drive_angle), float(pitch), shape=(ny, nx))


def row(n: int, pitch: float, origin: tuple[float, float] = (0.0, 0.0), drive_angle: float = 0.0) -> CellArray:
    """A single row of ``n`` cells along +x at spacing ``pitch`` (m): the paper's 1-D array."""
    if n < 1:
        raise ValueError(f"a row needs at least one cell (n >= 1), got {n}")
    return grid(n, 1, pitch, origin, drive_angle)


def from_points(points, pitch: float | None = None, drive_angle: float = 0.0) -> CellArray:
    """Cells at arbitrary ``points`` ((n, 2), m). ``pitch`` defaults to the median nearest-neighbour distance."""
    pos = np.asarray(points, dtype=float)
    if pos.ndim != 2 or pos.shape[-1] != 2 or len(pos) == 0:
        raise ValueError(f"points must be a non-empty list of [x, y] pairs, got shape {pos.shape}")
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
        raise ValueError("wheel offsets must be two finite [x, y] offsets in m, one per wheel")
    if np.allclose(off[0], off[1]):
        raise ValueError("the two wheels of a cell must sit at different points (wheel offsets)")
    U = cells.drive_directions
    pos = cells.positions[:, None, :] + off[None, :, 0, None] * U[:, None, 0, :] + off[None, :, 1, None] * U[:, None, 1, :]
    dirs = np.empty((cells.n, 2, 2, 2))
    for k in range(2):
        u = U[:, k]
        dirs[:, k, 0] = u
        dirs[:, k, 1] = np.column_stack([-u[:, 1], u[:, 0]])
    return _one_wheel_contacts(cells, pos.reshape(-1, 2), dirs.reshape(-1, 2, 2), 2)


def _one_wheel_contacts(cells: CellArray, pos: np.ndarray, dirs: np.ndarray, k: int) -> CellArray:
    """A contact layer of ``k`` single-wheel contacts per cell (contact ``k i + w`` is wheel w of cell i)."""
    n = cells.n
    active = np.tile([True, False], (k * n, 1))
    wheel_of = np.column_stack([np.tile(np.arange(k), n), np.full(k * n, -1)])
    return CellArray(pos, dirs, cells.pitch, None, active, np.repeat(np.arange(n), k), wheel_of)


def _sites(i, j, pitch: float, hexagonal: bool):
    """x, y (m) of lattice site column ``i``, row ``j``: square, or hexagonal (odd rows shifted by half a pitch, rows
    pitch sqrt(3)/2 apart, so that every neighbour is a pitch away)."""
    i, j = np.asarray(i), np.asarray(j)
    if not hexagonal:
        return i * pitch, j * pitch
    return (i + 0.5 * (j % 2)) * pitch, j * pitch * np.sqrt(3) / 2


def hexagonal(nx: int, ny: int, pitch: float, origin: tuple[float, float] = (0.0, 0.0),
              drive_angle: float = 0.0) -> CellArray:
    """A hexagonal lattice of ``ny`` rows of ``nx`` cells, neighbours ``pitch`` (m) apart: rows ``pitch sqrt(3)/2``
    apart, odd rows shifted by half a pitch, first cell at ``origin`` (m). Cell ``j * nx + i`` is column i, row j.
    Each cell has six network ports (at 0, 60, ..., 300 degrees from its wheel-0 drive direction ``drive_angle``,
    rad) and takes its command as a velocity along two orthogonal axes; its three wheels are the contact layer
    :func:`three_wheels`.

    >>> hexagonal(2, 2, 0.1).positions.round(4).tolist()
    [[0.0, 0.0], [0.1, 0.0], [0.05, 0.0866], [0.15, 0.0866]]
    """
    if nx < 1 or ny < 1:
        raise ValueError(f"a lattice needs at least one column and one row (nx, ny >= 1), got {nx} x {ny}")
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny))
    x, y = _sites(ii.ravel(), jj.ravel(), pitch, hexagonal=True)
    pos = np.column_stack([x, y]) + np.asarray(origin, dtype=float)
    return CellArray(pos, _drive_directions(len(pos), drive_angle), float(pitch), ports=np.full(len(pos), 6))


def three_wheels(cells: CellArray, radius: float | None = None) -> CellArray:
    """The contact layer of cells with three omni wheels at 120 degrees (commercial hexagonal omni-wheel
    conveyors): wheel w sits ``radius`` (m, default pitch/4) from the cell centre at angle -90 + 120 w degrees in the
    cell frame and drives tangentially, at 120 w degrees from the cell's wheel-0 axis, rolling freely along its
    axle. A cell commanded to move its surface at velocity V spins wheel w at ``V . u_w`` (m/s), the projection
    every omni-wheel drive makes; with all three wheels under a parcel any planar force can be produced. Contact
    ``3 i + w`` is wheel w of cell i.
    """
    r = cells.pitch / 4 if radius is None else float(radius)
    if not (np.isfinite(r) and 0 < r < cells.pitch / 2):
        raise ValueError(f"the wheel radius must lie between 0 and half the pitch ({cells.pitch / 2:g} m), got {r:g}")
    phi = -np.pi / 2 + 2 * np.pi * np.arange(3) / 3
    local_pos = r * np.column_stack([np.cos(phi), np.sin(phi)])  # (3, 2) in the cell frame
    local_dir = np.column_stack([-np.sin(phi), np.cos(phi)])  # tangential drive directions
    U = cells.drive_directions  # (n, 2, 2): the cell frame's axes in the world
    pos = cells.positions[:, None, :] + np.einsum("wk,nkj->nwj", local_pos, U)
    u = np.einsum("wk,nkj->nwj", local_dir, U)
    perp = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    return _one_wheel_contacts(cells, pos.reshape(-1, 2), np.stack([u, perp], axis=2).reshape(-1, 2, 2), 3)


@dataclass(frozen=True)
class Belt:
    """A plain conveyor belt: its centreline from ``start`` to ``end`` (m), ``width`` (m), surface ``speed`` (m/s,
    positive from start to end) and the ``spacing`` (m) of the support points that carry a parcel on it."""

    start: tuple[float, float]
    end: tuple[float, float]
    width: float
    speed: float
    spacing: float


def with_belts(cells: CellArray, contacts: CellArray, belts) -> tuple[CellArray, CellArray]:
    """``cells`` and their contact layer ``contacts`` with plain conveyor belts (:class:`Belt`) added: each belt is one
    more cell (no controller, no network ports, always at its own speed along its length, surface held still
    sideways) whose contacts are support points on a grid over its surface, ``spacing`` apart and including its
    edges. A belt must not cover a cell of the array. Returns the new (cells, contacts)."""
    if not belts:
        return cells, contacts
    pos, dirs, speed, c_pos, c_dirs, c_of = [], [], [], [], [], []
    for k, b in enumerate(belts):
        a, e = np.asarray(b.start, dtype=float), np.asarray(b.end, dtype=float)
        length = float(np.hypot(*(e - a)))
        if length <= 0:
            raise ValueError(f"a belt needs distinct start and end points, got {list(b.start)} twice")
        u = (e - a) / length
        v = np.array([-u[1], u[0]])
        nl = max(2, int(np.ceil(length / b.spacing - 1e-9)) + 1)
        nw = max(2, int(np.ceil(b.width / b.spacing - 1e-9)) + 1)
        s, w = np.meshgrid(np.linspace(0.0, length, nl), np.linspace(-b.width / 2, b.width / 2, nw))
        points = a + s.ravel()[:, None] * u + w.ravel()[:, None] * v
        along = np.abs((cells.positions - a) @ u - length / 2) <= length / 2 + 1e-12
        across = np.abs((cells.positions - a) @ v) <= b.width / 2 + 1e-12
        covered = np.flatnonzero(along & across & ~cells.belts)
        if len(covered):
            raise ValueError(f"the belt from {list(b.start)} to {list(b.end)} m covers cell {covered[0]} at "
                             f"{cells.positions[covered[0]].tolist()} m; belts feed or leave the array from beside it")
        pos.append((a + e) / 2)
        dirs.append([u, v])
        speed.append(b.speed)
        c_pos.append(points)
        c_dirs.append(np.broadcast_to([u, v], (len(points), 2, 2)))
        c_of.append(np.full(len(points), k))
    n_b = len(belts)
    belt_cells = CellArray(np.array(pos), np.array(dirs), cells.pitch, ports=np.zeros(n_b, int),
                           belt_speed=np.array(speed, dtype=float))
    belt_contacts = CellArray(np.vstack(c_pos), np.concatenate(c_dirs), cells.pitch, cell_of=np.concatenate(c_of))
    return combine([(cells, contacts), (belt_cells, belt_contacts)])


def combine(parts) -> tuple[CellArray, CellArray | None]:
    """One array from ``parts``, a list of (cells, contacts or None) pairs that share one pitch (m): cells are
    numbered part after part, each part keeps its own kind (square, hexagonal, ...) and contact layer. Returns the
    cells and their contact layer (None when every part is the paper's lumped cells). Raises ValueError for parts
    with different pitches or cells in the same place."""
    pitch = parts[0][0].pitch
    for k, (cells, _) in enumerate(parts):
        if not np.isclose(cells.pitch, pitch, rtol=1e-9):
            raise ValueError(f"the parts of a mixed array share one pitch ({pitch:g} m); part {k} has "
                             f"{cells.pitch:g} m")
    layers = [c if t is None else t for c, t in parts]
    offsets = np.cumsum([0] + [c.n for c, _ in parts])
    try:
        cells = CellArray(np.vstack([c.positions for c, _ in parts]),
                          np.concatenate([c.drive_directions for c, _ in parts]), pitch,
                          ports=np.concatenate([c.ports for c, _ in parts]),
                          belt_speed=np.concatenate([c.belt_speed for c, _ in parts]))
        if all(t is None for _, t in parts):
            return cells, None
        contacts = CellArray(np.vstack([t.positions for t in layers]),
                             np.concatenate([t.drive_directions for t in layers]), pitch, None,
                             np.concatenate([t.wheel_active for t in layers]),
                             np.concatenate([t.cell_of + off for t, off in zip(layers, offsets)]),
                             np.concatenate([t.wheel_of for t in layers]))
    except ValueError as exc:
        raise ValueError(f"the parts overlap: {exc}") from None
    return cells, contacts


MAP_HOLES = " ."
"""Map characters that mean no cell."""
MAP_CELLS = "o#E0123P><^v"
"""Map characters that mean a cell: ``o`` or ``#`` a plain one, ``E`` an entry cell, ``0``..``3`` a cell of exit k,
``P`` a parking cell (where a sorted parcel waits for its turn), ``>`` ``<`` ``^`` ``v`` a one-way cell (a parcel
on it may not move against the arrow: east, west, north, south; square lattices)."""
ONE_WAY = {">": 2, "<": 0, "^": 3, "v": 1}
"""One-way map arrows and the port (square cells: 0..3 = east, north, west, south) a parcel on the cell may not
move toward."""
MAP_MARKS = "E0123P><^v"
"""Map characters whose cells :func:`from_map` reports."""


def from_map(text: str, pitch: float, origin: tuple[float, float] = (0.0, 0.0), lattice: str = "square",
             drive_angle: float = 0.0) -> tuple[CellArray, dict[str, np.ndarray]]:
    """Cells drawn as text, one character per lattice site: the last line is the row at ``origin`` (m), lines
    above it go up in y, characters go along x at ``pitch`` (m). ``lattice`` "square" or "hex" (odd rows, counted
    from the bottom, shifted by half a pitch; rows pitch sqrt(3)/2 apart; six ports a cell). Characters: see
    :data:`MAP_CELLS` and :data:`MAP_HOLES`. Blank lines before and after the map are dropped. Returns the cells
    (numbered from the bottom row up, left to right) and, for each of :data:`MAP_MARKS` that occurs, the (n,) mask
    of its cells.

    >>> cells, marks = from_map("oo0\\nE.o", 0.1)
    >>> cells.positions.tolist()
    [[0.0, 0.0], [0.2, 0.0], [0.0, 0.1], [0.1, 0.1], [0.2, 0.1]]
    >>> marks["E"].tolist(), marks["0"].tolist()
    ([True, False, False, False, False], [False, False, False, False, True])
    """
    lines = text.split("\n")
    while lines and not lines[0].strip():
        lines.pop(0)
    while lines and not lines[-1].strip():
        lines.pop()
    cols, rows, chars = [], [], []
    for j, line in enumerate(reversed(lines)):
        for i, ch in enumerate(line.rstrip()):
            if ch in MAP_HOLES:
                continue
            if ch not in MAP_CELLS:
                raise ValueError(f"unknown character {ch!r} on line {len(lines) - j}, column {i + 1} "
                                 f"(cells: {MAP_CELLS!r}; no cell: space or '.')")
            cols.append(i)
            rows.append(j)
            chars.append(ch)
    if not chars:
        raise ValueError("the map has no cells")
    pos = np.column_stack(_sites(cols, rows, pitch, lattice == "hex")) + np.asarray(origin, dtype=float)
    chars = np.array(chars)
    ports = np.full(len(pos), 6 if lattice == "hex" else 4)
    cells = CellArray(pos, _drive_directions(len(pos), drive_angle), float(pitch), ports=ports)
    if lattice == "hex" and np.isin(chars, list(ONE_WAY)).any():
        raise ValueError("one-way arrows (> < ^ v) are for square lattices")
    return cells, {m: chars == m for m in MAP_MARKS if (chars == m).any()}


def cell_outlines(cells: CellArray, contacts: CellArray | None = None, scale: float = 1.0) -> list[np.ndarray]:
    """Each cell's outline as a (k, 2) array of corners (m), for pictures: a square of side ``pitch`` along the
    drive directions (four ports), a hexagon of apothem ``pitch / 2`` (six ports), and for a belt the rectangle its
    support points span (from ``contacts``, the layer holding them). ``scale`` shrinks cells about their centres
    (belts keep their size)."""
    out = []
    sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * cells.pitch / 2
    a = np.deg2rad(30 + 60 * np.arange(6))
    hx = np.column_stack([np.cos(a), np.sin(a)]) * cells.pitch / np.sqrt(3)
    for i in range(cells.n):
        U = cells.drive_directions[i]
        if cells.belts[i]:
            pts = contacts.positions[contacts.cell_of == i] - cells.positions[i]
            s, w = pts @ U[0], pts @ U[1]
            local = np.array([[s.min(), w.min()], [s.max(), w.min()], [s.max(), w.max()], [s.min(), w.max()]])
            out.append(cells.positions[i] + local @ U)
        else:
            local = hx if cells.ports[i] == 6 else sq
            out.append(cells.positions[i] + scale * local @ U)
    return out
