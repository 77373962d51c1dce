"""Who can talk to whom: each cell's ports and the neighbour on each (paper Section 2.3).

A cell has one port per neighbour direction (4 on a square layout, east/north/west/south in the cell's own frame,
counter-clockwise from the drive direction of wheel 0; 6 on a hexagonal one, every 60 degrees from it; none on a
plain conveyor belt). An array mixing kinds has as many port columns as its cells have at most. A port with no
neighbour, or whose link or neighbour is dead,
is simply silent. No cell has an address: a cell knows only its ports, and ids here are the simulator's bookkeeping.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from virtual_vehicle.model.layout import CellArray
from virtual_vehicle.model.state_data import array, fields

GRID_PORTS = ("east", "north", "west", "south")
SECTOR_MARGIN = 1e-6
"""rad by which a neighbour's bearing must lie inside half a port's sector (:func:`from_layout`): far above the
rounding of positions, far below any bearing a layout means."""


@dataclass(frozen=True, eq=False)
class Topology:
    """Neighbour links of an array.

    Attributes:
        neighbor: (n, P) id of the cell on each port, -1 where there is none.
        back_port: (n, P) the port of that neighbour which leads back here, -1 where there is none.
        link_up: (n, P) False where the link is dead (a dead cell has every link down, both ways).
        alive: (n,) False for dead cells (no drive, no messages).
    """

    neighbor: np.ndarray
    back_port: np.ndarray
    link_up: np.ndarray
    alive: np.ndarray

    @property
    def n(self) -> int:
        """Number of cells."""
        return self.neighbor.shape[0]

    @property
    def ports(self) -> int:
        """Links (ports) per cell."""
        return self.neighbor.shape[1]

    @cached_property
    def connected(self) -> np.ndarray:
        """(n, P) True where a message sent on the port can arrive: a neighbour, the link up, both cells alive
        (computed once: a topology's arrays are not changed after it is made; faults make a new one)."""
        return self.link_up & (self.neighbor >= 0)

    def to_data(self) -> dict:
        """The links as data: ``neighbor``, ``back_port``, ``link_up`` (n, P) and ``alive`` (n,)."""
        return {"neighbor": self.neighbor, "back_port": self.back_port, "link_up": self.link_up, "alive": self.alive}

    @classmethod
    def from_data(cls, d, where: str = "topology") -> "Topology":
        """The topology :meth:`to_data` wrote; raises ValueError for data of other keys, dtypes or shapes, or ids
        out of range."""
        d = fields(d, ("neighbor", "back_port", "link_up", "alive"), where)
        neighbor = array(d, "neighbor", "i", (None, None), where)
        n, P = neighbor.shape
        back = array(d, "back_port", "i", (n, P), where)
        if not ((neighbor >= -1) & (neighbor < n) & (back >= -1) & (back < P)).all():
            raise ValueError(f"{where}: a neighbour or back port out of range")
        return cls(neighbor, back, array(d, "link_up", "b", (n, P), where), array(d, "alive", "b", (n,), where))

    def with_faults(self, dead_cells=(), dead_links=()) -> "Topology":
        """A copy with cells (ids) dead and links ((cell, port) pairs) down, both directions of each."""
        alive = self.alive.copy()
        alive[list(dead_cells)] = False
        up = self.link_up.copy()
        for cell, port in dead_links:
            _cut(up, self, int(cell), int(port))
        for cell in np.flatnonzero(~alive):
            for port in range(self.ports):
                _cut(up, self, int(cell), port)
        return replace(self, link_up=up, alive=alive)


def _cut(up: np.ndarray, topo: Topology, cell: int, port: int) -> None:
    up[cell, port] = False
    j = topo.neighbor[cell, port]
    if j >= 0:
        up[j, topo.back_port[cell, port]] = False


def from_layout(cells: CellArray, ports: int | None = None, reach: float = 1.5) -> Topology:
    """Neighbour links of ``cells``: on each of a cell's ports (``cells.ports``, or ``ports`` for every cell;
    evenly spaced, starting at the drive direction of wheel 0), the nearest cell within ``reach`` pitches whose
    bearing is within half a sector of it by more than :data:`SECTOR_MARGIN` (rad); a link exists only where the two
    cells choose each other. A cell on the boundary of two sectors belongs to neither: on a square lattice the
    diagonal cell (at 45 degrees) would otherwise fall to one port or the other by the rounding of the positions, and
    where the straight neighbour on that port is missing (a hole) the two cells would link across the hole's corner.
    So a square lattice needs its cells' wheel 0 along a lattice axis: turned 45 degrees, every straight neighbour
    lies on a boundary and each port finds the diagonal cell in front of it.

    >>> from virtual_vehicle.model.layout import grid
    >>> t = from_layout(grid(3, 2, 0.1))
    >>> t.neighbor[0].tolist(), t.neighbor[4].tolist()  # cell 0: east is cell 1, north is cell 3
    ([1, 3, -1, -1], [5, -1, 3, 1])
    """
    n = cells.n
    own = cells.ports if ports is None else np.full(n, int(ports), dtype=np.int64)
    P = max(1, int(own.max()))
    neighbor = np.full((n, P), -1, dtype=np.int64)
    pairs = cells.tree.query_pairs(reach * cells.pitch, output_type="ndarray")
    if len(pairs):
        i = np.concatenate([pairs[:, 0], pairs[:, 1]])
        j = np.concatenate([pairs[:, 1], pairs[:, 0]])
        keep = (own[i] > 0) & (own[j] > 0)
        i, j = i[keep], j[keep]
        d = cells.positions[j] - cells.positions[i]
        u = cells.drive_directions[i, 0]
        bearing = np.arctan2(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0], u[:, 0] * d[:, 0] + u[:, 1] * d[:, 1])
        sector = 2 * np.pi / own[i]
        k = np.round(bearing / sector)
        inside = np.abs(bearing - k * sector) < sector / 2 - SECTOR_MARGIN  # clear of the boundary to the next port
        i, j, d = i[inside], j[inside], d[inside]
        port = k[inside].astype(np.int64) % own[i]
        dist = np.hypot(d[:, 0], d[:, 1])
        order = np.lexsort((j, dist))  # nearest first; ties by id for determinism
        slot, first = np.unique((i * P + port)[order], return_index=True)  # each port takes its nearest candidate
        neighbor.flat[slot] = j[order][first]
    back = np.full((n, P), -1, dtype=np.int64)
    a, p = np.nonzero(neighbor >= 0)
    b = neighbor[a, p]
    match = neighbor[b] == a[:, None]  # the ports of b that lead back to a
    mutual = match.sum(axis=1) == 1
    back[a[mutual], p[mutual]] = np.argmax(match[mutual], axis=1)
    neighbor[back < 0] = -1  # links must be mutual
    return Topology(neighbor, back, neighbor >= 0, np.ones(n, dtype=bool))
