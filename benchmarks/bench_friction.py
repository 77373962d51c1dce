"""Friction-law benchmark (issue: real cells). Prints figures; asserts nothing about time.

Wall-clock cost per simulated second of the stick-slip law (a complementarity problem per 1 ms step) against the
paper's Coulomb law (event-driven), for 1 and 50 parcels. Each parcel sits in its own 4 x 4-cell trap whose wheels
push toward the trap's centre at 0.5 m/s, on a 40 x 25 grid (pitch 0.1 m).

Run: ``make bench`` (or ``python benchmarks/bench_friction.py``).
"""

from __future__ import annotations

import time

import numpy as np

from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws


def traps(cells, size=4):
    """Per-cell velocities pushing toward the centre of each size x size block; the block centres (m)."""
    ny, nx = cells.shape
    i = np.arange(cells.n) % nx
    j = np.arange(cells.n) // nx
    centre = np.column_stack([(i // size) * size + (size - 1) / 2, (j // size) * size + (size - 1) / 2]) * cells.pitch
    v = 0.5 * np.sign(centre - cells.positions)
    centres = np.array([[(a * size + (size - 1) / 2) * cells.pitch, (b * size + (size - 1) / 2) * cells.pitch]
                        for b in range(ny // size) for a in range(nx // size)])
    return v, centres


def cost(law, n_parcels, duration=1.0):
    cells = layout.grid(40, 25, 0.1)
    velocities, centres = traps(cells)
    spec = parcel.rectangle(0.33, 0.31, 1.2, 0.4, mu_static=0.5)
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    steps = 0
    for c in centres[:n_parcels]:
        model = ParcelModel(cells, spec, fields.PerCell(tuple(map(tuple, velocities))).velocities(cells), law)
        y0 = [*(c + rng.uniform(-0.03, 0.03, 2)), rng.uniform(-0.2, 0.2), 0, 0, 0]
        tr = integrate(model, y0, 0.0, duration, dt=1e-3, sample_dt=0.01)
        assert tr.status == "completed"
        steps += tr.segments
    return (time.perf_counter() - start) / duration, steps


def main() -> None:
    print("# Cost per simulated second: stick-slip (1 ms steps) vs the paper's Coulomb law (event-driven)")
    print(f"{'law':<28}{'parcels':>8}{'wall s / sim s':>16}{'per parcel':>12}{'segments/steps':>16}")
    for name, law in (("Coulomb (paper), event", laws.CoulombLaw()), ("stick-slip, dt = 1 ms", laws.StickSlipLaw())):
        for n in (1, 50):
            c, steps = cost(law, n)
            print(f"{name:<28}{n:>8}{c:>16.3f}{c / n:>12.4f}{steps:>16}")


if __name__ == "__main__":
    main()
