"""Performance side by side (issue: performance at facility scale). Prints tables; asserts nothing about time.

(a) The paper's method taken literally (eq. 19 over all n cells with the mask matrix and an explicit inverse, then
    eqs. 22/24 by direct summation, at every right-hand-side evaluation) against ours (eq. 19 reduced to the 3x3
    moment system, solved once per support set; eqs. 23/29 as cached constants), both stepped by the same RK4 at
    the same step: wall time per simulated second and how far apart they end.
(b) Event-driven against fixed-step integration at equal accuracy: the final-position error against a converged
    reference (event-driven, rtol 1e-13) and the wall time, for both friction laws of the paper.

Scale and memory (c, d) are ``bench_scale.py``. Run everything with ``make bench``; record in RESULTS.md.
"""

from __future__ import annotations

import platform
import time

import numpy as np

from virtual_vehicle import fields, friction, layout, parcel
from virtual_vehicle.dynamics import ParcelModel, integrate
from virtual_vehicle.parcel import supporting_cells
from virtual_vehicle.reference import paper_normal_forces

CELLS = layout.grid(30, 30, 0.1)
SPEC = parcel.rectangle(0.4, 0.3, 2.0, 1.0)
V = fields.Uniform((0.2, 0.0)).velocities(CELLS)
Y0 = np.array([0.52, 1.47, 0.3, 0.0, 0.0, 0.0])  # a tilted box: many support changes
LAWS = {"coulomb": friction.CoulombLaw(), "viscous": friction.ViscousLaw()}


def literal_rhs(law):
    """The state derivative the paper's way: every evaluation builds the (n+3) system, masks it and inverts."""
    W = SPEC.weight(9.81)
    everything = np.ones(CELLS.n, bool)

    def rhs(t, y):
        under = supporting_cells(SPEC, y, CELLS.positions, CELLS.tree)
        mask = np.zeros(CELLS.n, bool)
        mask[under] = True
        N = paper_normal_forces(CELLS.positions, mask & everything, y[:2], W)[under]  # eq. 19, literal
        fx, fy, tau = law.wrench(CELLS.positions[under], N, V[under], CELLS.drive_directions[under], SPEC.mu, y)
        return np.array([y[3], y[4], y[5], fx / SPEC.mass, fy / SPEC.mass, tau / SPEC.inertia])

    return rhs


def rk4(rhs, y, t1, dt):
    t = 0.0
    while t < t1 - 1e-12:
        h = min(dt, t1 - t)
        k1 = rhs(t, y)
        k2 = rhs(t + h / 2, y + h / 2 * k1)
        k3 = rhs(t + h / 2, y + h / 2 * k2)
        k4 = rhs(t + h, y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
    return y


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def part_a(seconds: float = 0.5, dt: float = 1e-3) -> None:
    print(f"## (a) Paper's eq. 19 literally at every evaluation vs ours ({CELLS.n} cells, RK4 dt = {dt * 1e3:g} ms, "
          f"{seconds:g} s simulated)")
    print(f"{'law':<9}{'literal s/sim s':>17}{'ours s/sim s':>14}{'speed-up':>10}{'|end diff| (m)':>16}")
    for name, law in LAWS.items():
        t_lit, y_lit = timed(lambda: rk4(literal_rhs(law), Y0.copy(), seconds, dt))
        model = ParcelModel(CELLS, SPEC, V, law)
        t_ours, tr = timed(lambda: integrate(model, Y0, 0.0, seconds, mode="fixed", dt=dt, sample_dt=seconds))
        diff = float(np.abs(tr.states[-1, :2] - y_lit[:2]).max())
        print(f"{name:<9}{t_lit / seconds:>17.3f}{t_ours / seconds:>14.3f}{t_lit / t_ours:>10.1f}{diff:>16.1e}")
    print("(ours also solves lift-off; the literal method has none, so they agree while no cell lifts off)")
    print()


def part_b(seconds: float = 5.0) -> None:
    print(f"## (b) Event-driven vs fixed-step at equal accuracy (one parcel, 30x30, {seconds:g} s simulated)")
    print(f"{'law':<9}{'integrator':<30}{'end error (m)':>15}{'wall (ms)':>11}{'x real time':>13}")
    for name, law in LAWS.items():
        ref = integrate(ParcelModel(CELLS, SPEC, V, law), Y0, 0.0, seconds, rtol=1e-13, atol=1e-15,
                        sample_dt=seconds).states[-1]
        rows = []
        for rtol in (1e-6, 1e-10):
            wall, tr = timed(lambda: integrate(ParcelModel(CELLS, SPEC, V, law), Y0, 0.0, seconds, rtol=rtol,
                                               sample_dt=seconds))
            rows.append((f"event-driven rtol {rtol:g}", float(np.abs(tr.states[-1, :2] - ref[:2]).max()), wall))
        for dt in (1e-2, 1e-3, 1e-4):
            wall, tr = timed(lambda: integrate(ParcelModel(CELLS, SPEC, V, law), Y0, 0.0, seconds, mode="fixed",
                                               dt=dt, sample_dt=seconds))
            rows.append((f"fixed-step RK4 dt {dt * 1e3:g} ms", float(np.abs(tr.states[-1, :2] - ref[:2]).max()),
                         wall))
        for label, err, wall in rows:
            print(f"{name:<9}{label:<30}{err:>15.1e}{wall * 1e3:>11.1f}{seconds / wall:>13.0f}")
    print("(fixed steps are first order across support changes: equal accuracy needs dt ~ error / 3)")
    print()


def main() -> None:
    print(f"# virtual_vehicle performance — {platform.machine()}, Python {platform.python_version()}, "
          f"numpy {np.__version__}")
    print()
    part_a()
    part_b()


if __name__ == "__main__":
    main()
