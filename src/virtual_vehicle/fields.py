"""Wheel-velocity fields: the surface velocity (m/s) each cell's wheels give, as constant fields (paper 4: "each of
the cells is assumed to be spinning at a constant speed").

A field maps a :class:`~virtual_vehicle.layout.CellArray` to an (n, 2) array of cell velocities in m/s; the
component of a cell's velocity along each wheel's drive direction is that wheel's surface speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ScenarioError
from .layout import CellArray


@dataclass(frozen=True)
class Uniform:
    """Every cell drives at the same ``velocity`` (m/s)."""

    velocity: tuple[float, float]

    def velocities(self, cells: CellArray) -> np.ndarray:
        return np.tile(np.asarray(self.velocity, dtype=float), (cells.n, 1))


@dataclass(frozen=True)
class Inward:
    """Each wheel spins toward ``center`` (m) at ``speed`` (m/s): per axis ``speed * sign(center - X_i)``, the
    paper's 2x2 inward field (eq. 21) on any array. A cell level with the centre along an axis leaves that wheel
    stopped."""

    center: tuple[float, float]
    speed: float

    def velocities(self, cells: CellArray) -> np.ndarray:
        return self.speed * np.sign(np.asarray(self.center, dtype=float) - cells.positions)


@dataclass(frozen=True)
class ReversedEnd:
    """All cells drive at ``velocity`` (m/s) except the cells at the far end along it, which drive the opposite way:
    the 1-D oscillator of the authors' earlier paper (Section 3), and its 2-D version on a grid ("the last column").
    """

    velocity: tuple[float, float]

    def velocities(self, cells: CellArray) -> np.ndarray:
        v = np.asarray(self.velocity, dtype=float)
        speed = float(np.linalg.norm(v))
        if speed == 0:
            raise ScenarioError("field.velocity", "a reversed-end field needs a non-zero velocity")
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
        v = np.asarray(self.values, dtype=float)
        if v.shape != (cells.n, 2):
            raise ScenarioError("field.velocities", f"needs one [vx, vy] per cell: {cells.n} rows, got shape {v.shape}")
        return v
