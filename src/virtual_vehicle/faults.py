"""Broken hardware (paper Section 1, redundancy): dead cells, stuck and free-spinning wheels, dead links, stuck
sensors, listed in a scenario or drawn at random with given rates and a seed.

What each fault does:

* a dead cell neither drives (its wheels are held still) nor sends or receives sentences; it still carries weight;
* a stuck wheel is held still whatever its cell commands (a brake under the viscous and stick-slip laws; under the
  paper's Coulomb law a still wheel pushes nothing);
* a free-spinning wheel gives no traction along its drive direction (coulomb and stick_slip laws only: the
  paper's viscous law acts on the whole slip vector of a cell and has no way to leave one direction free);
* a dead link carries no sentences either way;
* a stuck sensor reads 1 (stuck on) or 0 (stuck off) always.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ScenarioError


@dataclass(frozen=True, eq=False)
class Faults:
    """The faults of a run, resolved to masks over ``n`` cells (``S`` sensors each).

    Attributes:
        dead_cells: (n,) bool. stuck_wheels, free_wheels: (n, 2) bool, [cell, wheel]. dead_links: [(cell, port)]
        (each link once). stuck_on, stuck_off: (n, S) bool sensor masks.
    """

    dead_cells: np.ndarray
    stuck_wheels: np.ndarray
    free_wheels: np.ndarray
    dead_links: tuple[tuple[int, int], ...]
    stuck_on: np.ndarray
    stuck_off: np.ndarray

    @property
    def held(self) -> np.ndarray:
        """(n, 2) wheels held still: stuck, or on a dead cell."""
        return self.stuck_wheels | self.dead_cells[:, None]

    def any(self) -> bool:
        """True when anything is broken."""
        return bool(self.dead_cells.any() or self.stuck_wheels.any() or self.free_wheels.any() or self.dead_links
                    or self.stuck_on.any() or self.stuck_off.any())

    def summary(self) -> dict:
        """JSON-ready lists of what is broken."""
        return {"dead_cells": np.flatnonzero(self.dead_cells).tolist(),
                "stuck_wheels": np.argwhere(self.stuck_wheels).tolist(),
                "free_wheels": np.argwhere(self.free_wheels).tolist(),
                "dead_links": [list(x) for x in self.dead_links],
                "stuck_on_sensors": np.argwhere(self.stuck_on).tolist(),
                "stuck_off_sensors": np.argwhere(self.stuck_off).tolist()}

    def hold(self, wheel_speeds: np.ndarray) -> np.ndarray:
        """``wheel_speeds`` ((n, 2) m/s along each drive direction) with the held wheels at zero."""
        return np.where(self.held, 0.0, wheel_speeds)

    def hold_velocities(self, velocities: np.ndarray, drive_directions: np.ndarray) -> np.ndarray:
        """Cell surface velocities ((n, 2) m/s, world frame) with the held wheels' components removed."""
        speeds = np.einsum("ij,ikj->ik", velocities, drive_directions)
        return np.einsum("ik,ikj->ij", self.hold(speeds), drive_directions)


def resolve(spec, cells, sensors_per_cell: int, neighbor: np.ndarray, listed_links=()) -> Faults:
    """The faults of scenario table ``spec`` (:class:`~virtual_vehicle.scenario.FaultSpec`) on ``cells``: the listed
    ones plus those drawn with the rates from ``numpy.random.default_rng(spec.seed)`` (in this order: cells, wheels
    stuck, wheels free, links, sensors). ``neighbor`` is the topology's (n, P) neighbour table; ``listed_links``
    further dead links. Raises ScenarioError for a listed item that does not exist."""
    n, S = cells.n, sensors_per_cell
    rng = np.random.default_rng(spec.seed)
    dead = np.zeros(n, bool)
    for k, c in enumerate(spec.dead_cells):
        if c >= n:
            raise ScenarioError(f"faults.dead_cells[{k}]", f"cell {c} does not exist (the array has {n})")
        dead[c] = True
    wheels = {}
    for name in ("stuck_wheels", "free_wheels"):
        mask = np.zeros((n, 2), bool)
        for k, (c, w) in enumerate(getattr(spec, name)):
            if c >= n:
                raise ScenarioError(f"faults.{name}[{k}]", f"cell {c} does not exist (the array has {n})")
            mask[c, w] = True
        wheels[name] = mask
    dead |= rng.random(n) < spec.dead_cell_rate
    wheels["stuck_wheels"] |= rng.random((n, 2)) < spec.stuck_wheel_rate
    wheels["free_wheels"] |= (rng.random((n, 2)) < spec.free_wheel_rate) & ~wheels["stuck_wheels"]
    links = {tuple(map(int, x)) for x in listed_links}
    i, p = np.nonzero(neighbor >= 0)
    once = i < neighbor[i, p]  # each link from its lower-numbered end
    for a, b in zip(i[once], p[once]):
        if rng.random() < spec.dead_link_rate:
            links.add((int(a), int(b)))
    stuck = rng.random((n, S)) < spec.stuck_sensor_rate
    on = rng.random((n, S)) < 0.5
    return Faults(dead, wheels["stuck_wheels"], wheels["free_wheels"], tuple(sorted(links)), stuck & on,
                  stuck & ~on)
