"""Broken hardware (paper Section 1, redundancy): dead cells, stuck and free-spinning wheels, dead links, stuck
sensors, listed in a scenario or drawn at random with given rates and a seed.

What each fault does:

* a dead cell neither drives nor sends or receives sentences; it still carries weight; its wheels are held still,
  or (``dead_wheels = "free"``) spin freely, as a free-spinning wheel below;
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
    """The faults of scenario table ``spec`` (:class:`~virtual_vehicle.config.scenario.FaultSpec`) on ``cells``: the
    listed ones plus those drawn with the rates from ``numpy.random.default_rng(spec.seed)`` (in this order: cells,
    wheels stuck, wheels free, links, sensors). ``neighbor`` is the topology's (n, P) neighbour table; ``listed_links``
    further dead links. Raises ValueError for a listed item that does not exist."""
    n, S = cells.n, sensors_per_cell
    rng = np.random.default_rng(spec.seed)
    dead = np.zeros(n, bool)
    for k, c in enumerate(spec.dead_cells):
        _check_cell(c, n, f"dead_cells[{k}]")
        dead[c] = True
    wheels = {}
    for name in ("stuck_wheels", "free_wheels"):
        mask = np.zeros((n, 2), bool)
        for k, (c, w) in enumerate(getattr(spec, name)):
            _check_cell(c, n, f"{name}[{k}]")
            mask[c, w] = True
        wheels[name] = mask
    dead |= rng.random(n) < spec.dead_cell_rate
    wheels["stuck_wheels"] |= rng.random((n, 2)) < spec.stuck_wheel_rate
    wheels["free_wheels"] |= (rng.random((n, 2)) < spec.free_wheel_rate) & ~wheels["stuck_wheels"]
    if spec.dead_wheels == "free":  # (no draw: the draws stay those of "held"); a stuck wheel stays held
        wheels["free_wheels"] |= dead[:, None] & ~wheels["stuck_wheels"]
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


def later(now: Faults, event, n: int, sensors_per_cell: int) -> Faults:
    """The faults after ``event`` (:class:`~virtual_vehicle.config.scenario.FaultEvent`) adds its own to ``now``; a
    fault never heals by itself, but the cells the event lists as ``revived_cells`` (repaired) are dead no more.
    Raises ValueError for an item that does not exist or a cell both killed and revived."""
    dead = now.dead_cells.copy()
    stuck = now.stuck_wheels.copy()
    on, off = now.stuck_on.copy(), now.stuck_off.copy()
    for k, c in enumerate(event.dead_cells):
        _check_cell(c, n, f"dead_cells[{k}]")
        dead[c] = True
    for k, c in enumerate(event.revived_cells):
        _check_cell(c, n, f"revived_cells[{k}]")
        if c in event.dead_cells:
            raise ValueError(f"revived_cells[{k}] names cell {c}, which the same event kills")
        dead[c] = False
    for k, (c, w) in enumerate(event.stuck_wheels):
        _check_cell(c, n, f"stuck_wheels[{k}]")
        stuck[c, w] = True
    for name, mask in (("stuck_on", on), ("stuck_off", off)):
        for k, (c, s) in enumerate(getattr(event, name)):
            _check_cell(c, n, f"{name}[{k}]")
            if s >= sensors_per_cell:
                raise ValueError(f"{name}[{k}] names sensor {s}, which does not exist: cells have {sensors_per_cell}")
            mask[c, s] = True
    links = set(now.dead_links)
    for k, (c, port) in enumerate(event.dead_links):
        _check_cell(c, n, f"dead_links[{k}]")
        links.add((int(c), int(port)))
    return Faults(dead, stuck, now.free_wheels, tuple(sorted(links)), on, off & ~on)


def _check_cell(c: int, n: int, item: str) -> None:
    if c >= n:
        raise ValueError(f"{item} names cell {c}, which does not exist (the array has {n})")
