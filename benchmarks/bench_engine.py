"""Engine benchmarks (issue: dynamics engine). Prints figures; asserts nothing about time.

1. Real-time factor of one parcel crossing a 30 x 30 grid (pitch 0.1 m, parcel 0.4 x 0.3 m, uniform field 0.2 m/s,
   5 s simulated, viscous law) with the event-driven and the fixed-step integrators, and how far apart they end.
2. Time to compute the normal forces for 10, 100 and 1000 supporting cells: ours (3x3 moment system with lift-off)
   against a literal evaluation of the paper's eq. 19 (mask matrices and an (m+3)-square inverse).

Run: ``make bench`` (or ``python benchmarks/bench_engine.py``).
"""

from __future__ import annotations

import platform
import time

import numpy as np

from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.physics import laws
from virtual_vehicle.physics.contact import normal_forces
from virtual_vehicle.physics.reference import paper_normal_forces


def best_of(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def crossing(mode: str, theta: float = 0.0, **kw):
    cells = layout.grid(30, 30, 0.1)
    spec = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
    velocities = fields.Uniform((0.2, 0.0)).velocities(cells)

    def run():
        model = ParcelModel(cells, spec, velocities, laws.ViscousLaw())  # fresh: nothing cached between runs
        return integrate(model, [0.52, 1.47, theta, 0, 0, 0], 0.0, 5.0, mode=mode, sample_dt=0.01, **kw)

    return best_of(run, 5 if mode == "event" else 2)


def main() -> None:
    print(f"# virtual_vehicle engine benchmark — {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}, numpy {np.__version__}")
    print()
    print("## One parcel crossing a 30x30 grid (5 s simulated, viscous law)")
    print(f"{'integrator':<28}{'heading':>8}{'wall (ms)':>12}{'real-time x':>14}{'events':>8}{'end x (m)':>14}")
    ref = None
    for theta in (0.0, 0.3):
        for label, mode, kw in (("event-driven (DOP853)", "event", {}), ("fixed-step RK4 dt=1 ms", "fixed", {"dt": 1e-3})):
            wall, tr = crossing(mode, theta, **kw)
            if mode == "event":
                ref = tr.states[-1]
            diff = "" if mode == "event" else f"  |dx| vs event {np.abs(tr.states[-1] - ref)[:3].max():.1e}"
            print(f"{label:<28}{theta:>8.1f}{wall * 1e3:>12.1f}{tr.t_end / wall:>14.0f}{len(tr.events):>8}"
                  f"{tr.states[-1, 0]:>14.6f}{diff}")
    print("target: >= 200x real time (event-driven, heading 0)")
    print()
    print("## Normal forces for m supporting cells (one evaluation)")
    print(f"{'m':>6}{'ours (us)':>14}{'paper eq. 19 literal (us)':>28}{'max |diff| (N)':>18}")
    rng = np.random.default_rng(0)
    for m in (10, 100, 1000):
        side = int(np.ceil(np.sqrt(m)))
        xs, ys = np.meshgrid(np.arange(side) * 0.1, np.arange(side) * 0.1)
        pts = np.column_stack([xs.ravel(), ys.ravel()])[:m] + rng.normal(0, 1e-3, size=(m, 2))
        com = pts.mean(axis=0) + 0.01
        under = np.ones(m, bool)
        reps = 200 if m <= 100 else 10
        t_ours, n_ours = best_of(lambda: normal_forces(pts, com, 20.0), reps)
        t_paper, n_paper = best_of(lambda: paper_normal_forces(pts, under, com, 20.0), max(3, reps // 10))
        print(f"{m:>6}{t_ours * 1e6:>14.1f}{t_paper * 1e6:>28.1f}{np.abs(n_ours - n_paper).max():>18.2e}")


if __name__ == "__main__":
    main()
