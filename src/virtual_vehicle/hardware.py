"""Cell hardware: binary presence sensors (paper Sections 1 and 2.2).

Units: m. Each cell carries up to five phototransistors that see the shadow of a parcel above them. A sensor reads 1
when a parcel's footprint covers its point. Offsets are given in the cell's own frame (x along its wheel 0, y along
wheel 1); the default is the centre and the four edge midpoints, half a pitch out.

Imperfections: each reading is independently flipped from 0 to 1 with probability ``false_positive`` and from 1 to
0 with ``false_negative`` (one numpy Generator, seeded); faulty sensors are stuck on or stuck off.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .errors import ScenarioError
from .layout import CellArray
from .parcel import ParcelSpec, footprint_margins

MAX_SENSORS = 5


def default_offsets(pitch: float) -> np.ndarray:
    """Centre, then the east, north, west and south edge midpoints (cell frame), m."""
    h = pitch / 2
    return np.array([[0.0, 0.0], [h, 0.0], [0.0, h], [-h, 0.0], [0.0, -h]])


@dataclass(frozen=True, eq=False)
class Sensors:
    """The presence sensors of an array.

    Attributes:
        cells: the array.
        offsets: (S, 2) sensor offsets in each cell's frame, m (S <= 5).
        false_positive, false_negative: per-reading flip probabilities.
        stuck_on, stuck_off: (n, S) bool fault masks (stuck on wins if both).
        seed: seed of the noise; each run draws from its own ``numpy.random.default_rng(seed)``.
    """

    cells: CellArray
    offsets: np.ndarray
    false_positive: float = 0.0
    false_negative: float = 0.0
    stuck_on: np.ndarray | None = None
    stuck_off: np.ndarray | None = None
    seed: int = 0

    def __post_init__(self):
        off = np.asarray(self.offsets, dtype=float)
        if off.ndim != 2 or off.shape[1] != 2 or not 1 <= len(off) <= MAX_SENSORS or not np.all(np.isfinite(off)):
            raise ScenarioError("sensors.offsets", f"needs 1 to {MAX_SENSORS} finite [x, y] offsets in m")
        for name in ("false_positive", "false_negative"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ScenarioError(f"sensors.{name}", f"must be a probability in [0, 1], got {v}")
        object.__setattr__(self, "offsets", off)
        shape = (self.cells.n, len(off))
        for name in ("stuck_on", "stuck_off"):
            mask = getattr(self, name)
            mask = np.zeros(shape, bool) if mask is None else np.asarray(mask, dtype=bool)
            if mask.shape != shape:
                raise ScenarioError(f"sensors.{name}", f"fault mask must have shape {shape}")
            object.__setattr__(self, name, mask)

    @property
    def count(self) -> int:
        """Sensors per cell."""
        return len(self.offsets)

    @cached_property
    def points(self) -> np.ndarray:
        """(n, S, 2) world positions of every sensor, m."""
        u = self.cells.drive_directions  # (n, 2, 2): wheel 0 and wheel 1 directions
        return self.cells.positions[:, None, :] + self.offsets[None, :, 0, None] * u[:, None, 0, :] \
            + self.offsets[None, :, 1, None] * u[:, None, 1, :]

    @cached_property
    def _tree(self) -> cKDTree:
        return cKDTree(self.points.reshape(-1, 2))

    def covered(self, specs: list[ParcelSpec], states, active=None) -> np.ndarray:
        """(n, S) True where a (active) parcel's footprint covers the sensor point: the noiseless truth."""
        n, S = self.cells.n, self.count
        out = np.zeros(n * S, dtype=bool)
        flat = self.points.reshape(-1, 2)
        for k, (spec, y) in enumerate(zip(specs, states)):
            if active is not None and not active[k]:
                continue
            idx = np.asarray(self._tree.query_ball_point(np.asarray(y[:2], float), spec.radius * (1 + 1e-9)), int)
            if len(idx):
                out[idx[footprint_margins(spec, y, flat[idx]) > 0]] = True
        return out.reshape(n, S)

    def read(self, specs: list[ParcelSpec], states, rng: np.random.Generator, active=None) -> np.ndarray:
        """(n, S) readings: the truth, flipped at the false-positive/negative rates (drawn from ``rng``), then the
        stuck faults."""
        truth = self.covered(specs, states, active)
        r = rng.random(truth.shape)
        reading = np.where(truth, r >= self.false_negative, r < self.false_positive)
        return (reading | self.stuck_on) & ~(self.stuck_off & ~self.stuck_on)
