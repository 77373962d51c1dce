"""The seed paper's own results (Luntz, Messner, Choset, "Virtual Vehicle: parcel manipulation and dynamics with a
distributed actuator array", 1997), Section 4, and the 1-D row of the authors' earlier paper it recalls in
Section 2 (its ref. 13): each computed with the package's physics and engine, beside a closed form derived by hand.

Units: SI (m, s, rad, N, N/m, kg).
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from scipy.linalg import expm

from virtual_vehicle.analysis.classics.base import Result, new_figure, save_figure, write_table
from virtual_vehicle.analysis.equilibria import equilibria
from virtual_vehicle.config.scenario import load_scenario
from virtual_vehicle.engine.dynamics import ParcelModel, integrate

SEED = ("J. Luntz, W. Messner, H. Choset, \"Virtual Vehicle: parcel manipulation and dynamics with a distributed "
        "actuator array\" (1997)")


def inward_2x2(out: Path) -> Result:
    """The paper's 2x2 inward field (Section 4.3, eqs. 20-29) under Coulomb friction: R = 0 (eq. 26), a-hat
    diagonal (eq. 23), zero torque at every heading, and so an undamped oscillation toward the centre without
    turning, at the frequency a-hat gives, sqrt(2 mu g / d) (rad/s), d the pitch (m)."""
    sc, _ = load_scenario("paper_2x2_inward")
    setup = sc.build()
    cells, spec, law, g = setup.cells, setup.specs[0], setup.law, sc.gravity
    d, mu, weight = cells.pitch, spec.mu, spec.weight(g)
    centred = cells.positions - cells.positions.mean(axis=0)  # the paper's frame, eq. 20
    F = law.drive_vectors(setup.velocities, cells.active_directions)  # eq. 21
    R = centred[:, 0] * F[:, 1] - centred[:, 1] * F[:, 0]  # eq. 26
    y0 = np.asarray(setup.states[0], dtype=float)
    a = ParcelModel(cells, spec, setup.velocities, law, g).piece_at(y0).constants.a  # eq. 23
    eqs = equilibria(cells, spec, setup.velocities, law, headings=np.linspace(0, 2 * np.pi, 13), gravity=g)
    neutral = [e for e in eqs if e.rotation == "neutral" and e.heading_range is not None]
    turn = min(max((e.heading_range[1] - e.heading_range[0] for e in neutral), default=0.0), 2 * np.pi)
    tr = integrate(ParcelModel(cells, spec, setup.velocities, law, g), y0, 0.0, sc.duration, sample_dt=1e-3)
    t, x, y, th = tr.times, tr.states[:, 0], tr.states[:, 1], tr.states[:, 2]
    omega_closed = np.sqrt(2 * mu * g / d)  # eq. 23 with a-hat = -(2 mu W / d) I, over the mass
    omega_x, omega_y = _frequency(t, x), _frequency(t, y)
    numbers = {
        "R_max_abs_m": float(np.max(np.abs(R))),
        "a_hat_N_per_m": a.tolist(),
        "a_offdiag_over_diag": float(max(abs(a[0, 1]), abs(a[1, 0])) / max(abs(a[0, 0]), abs(a[1, 1]))),
        "a_diag_closed_N_per_m": float(-2 * mu * weight / d),
        "zero_torque_heading_range_rad": float(turn),
        "theta_drift_rad": float(np.max(np.abs(th - th[0]))),
        "omega_closed_rad_per_s": float(omega_closed),
        "omega_x_rad_per_s": omega_x,
        "omega_y_rad_per_s": omega_y,
        "amplitude_x_m": float(np.max(np.abs(x))),
        "support_events": len(tr.events),
    }
    passed = bool(numbers["R_max_abs_m"] < 1e-12 and numbers["a_offdiag_over_diag"] < 1e-12
                  and abs(a[0, 0] / numbers["a_diag_closed_N_per_m"] - 1) < 1e-9
                  and abs(a[1, 1] / numbers["a_diag_closed_N_per_m"] - 1) < 1e-9
                  and turn >= 2 * np.pi - 1e-9 and numbers["theta_drift_rad"] < 1e-12
                  and abs(omega_x / omega_closed - 1) < 1e-4 and abs(omega_y / omega_closed - 1) < 1e-4)
    out.mkdir(parents=True, exist_ok=True)
    table = write_table(out / "inward_2x2.csv", {
        "t": (t, "s"), "x": (x, "m"), "y": (y, "m"), "theta": (th, "rad"),
        "x_closed": (y0[0] * np.cos(omega_closed * t), "m"), "y_closed": (y0[1] * np.cos(omega_closed * t), "m")})
    fig, ax = new_figure(1, 2, 10, 3.8)
    _draw_2x2(ax[0, 0], cells, setup.velocities, spec, y0)
    ax1 = ax[0, 1]
    ax1.plot(t, 1e3 * x, color="tab:blue", lw=2.5, alpha=0.5, label="x, engine")
    ax1.plot(t, 1e3 * y, color="tab:orange", lw=2.5, alpha=0.5, label="y, engine")
    ax1.plot(t, 1e3 * y0[0] * np.cos(omega_closed * t), "k--", lw=0.9, label=r"$x_0\cos\sqrt{2\mu g/d}\,t$")
    ax1.plot(t, 1e3 * y0[1] * np.cos(omega_closed * t), "k:", lw=0.9, label=r"$y_0\cos\sqrt{2\mu g/d}\,t$")
    ax1.set_xlabel("t (s)")
    ax1.set_ylabel("centre of mass (mm)")
    ax1.set_title(f"oscillation: {omega_x:.6g} rad/s (closed form {omega_closed:.6g}); "
                  f"heading drift {numbers['theta_drift_rad']:.1g} rad", fontsize=9)
    ax1.legend(fontsize=8, loc="upper right", ncol=2)
    figure = save_figure(fig, out / "inward_2x2.png")
    return Result(
        "inward_2x2", "The 2x2 inward field: R = 0, a-hat diagonal, zero torque, an isotropic oscillation",
        f"{SEED}, Section 4.3.1, eqs. 20-26",
        "\"For simple, inward pointing fields, a-hat has elements only on the diagonal, meaning that the y force on "
        "the parcel, f_y, only depends on y_c and the x force on the parcel, f_x, only depends on x_c.\" (4.3.1); "
        "R = [0 0 0 0] (eq. 26), so the torque vanishes; with eq. 23 the parcel oscillates at sqrt(2 mu g / d) "
        "(derived here, not in the paper)",
        f"max |R_i| = {numbers['R_max_abs_m']:.1g} m; |a_xy / a_xx| = {numbers['a_offdiag_over_diag']:.1g}; "
        f"zero torque over {turn / np.pi:.3g} pi rad of heading (all); heading drift "
        f"{numbers['theta_drift_rad']:.1g} rad; "
        f"omega {omega_x:.7g} / {omega_y:.7g} rad/s (x / y) vs {omega_closed:.7g}",
        passed, "R and a_xy to 1e-12; a_xx, a_yy to 1e-9 of -2 mu W / d; omega to 1e-4 (period read from the "
        "trajectory's zero crossings)", numbers, [figure, table])


def _frequency(t: np.ndarray, x: np.ndarray) -> float:
    """Angular frequency (rad/s) from the mean spacing of upward zero crossings (linear interpolation)."""
    i = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    if len(i) < 2:
        return float("nan")
    tz = t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])
    return float(2 * np.pi / np.mean(np.diff(tz)))


def _draw_2x2(ax, cells, velocities, spec, y0):
    """The array, each cell's drive (arrows) and the parcel's outline at its start."""
    p = cells.positions
    ax.scatter(p[:, 0], p[:, 1], s=60, color="0.4", zorder=3, label="cells")
    ax.quiver(p[:, 0], p[:, 1], velocities[:, 0], velocities[:, 1], color="tab:red", angles="xy",
              scale_units="xy", scale=12, width=0.012, label="wheel velocity")
    c, s = np.cos(y0[2]), np.sin(y0[2])
    fp = spec.footprint @ np.array([[c, s], [-s, c]]) + y0[:2]
    ax.fill(fp[:, 0], fp[:, 1], alpha=0.15, color="tab:blue", label="parcel at t = 0")
    ax.plot(*y0[:2], "+", color="tab:blue", ms=10)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("2 x 2 array, each wheel pushing inward (eq. 21)", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")


def beam_forces(s: np.ndarray, xc: float, weight: float) -> np.ndarray:
    """Normal forces (N) of equal tensionless springs at ``s`` (m) under a rigid bar with its centre of mass at
    ``xc`` (m): the textbook beam on springs, the largest contact set whose forces are all non-negative (the
    package solves the same problem in 2-D with its own code, paper eqs. 3-19)."""
    s = np.asarray(s, dtype=float)
    for size in range(len(s), 1, -1):
        for subset in itertools.combinations(range(len(s)), size):
            ss = s[list(subset)]
            mean = ss.mean()
            plane = weight / size + weight * (xc - mean) * (s - mean) / np.sum((ss - mean) ** 2)
            inside = np.zeros(len(s), dtype=bool)
            inside[list(subset)] = True
            if np.all(plane[inside] >= -1e-12) and np.all(plane[~inside] <= 1e-12):
                return np.where(inside, plane, 0.0)
    raise ValueError("the bar tips: no contact set of two or more springs holds it")


def row_segments(scenario: str, sample_dt: float = 1e-3) -> tuple[list[dict], object, object]:
    """Simulate a bundled row scenario with the engine and compare each stretch between support changes with the
    closed-form oscillator of its contact set. Returns (one dict per stretch, the trajectory, the setup)."""
    sc, _ = load_scenario(scenario)
    setup = sc.build()
    cells, spec, law, g = setup.cells, setup.specs[0], setup.law, sc.gravity
    weight, mass, mu = spec.weight(g), spec.mass, spec.mu
    s = cells.positions[:, 0]
    drive = law.drive_vectors(setup.velocities, cells.active_directions)[:, 0]  # F (Coulomb) or V (viscous), eq. 22/33
    damping = mu * weight if law.damped else 0.0  # eq. 33's mu W (N s/m)
    lo, hi = spec.footprint[:, 0].min(), spec.footprint[:, 0].max()
    tr = integrate(ParcelModel(cells, spec, setup.velocities, law, g), setup.states[0], 0.0, sc.duration,
                   sample_dt=sample_dt)
    t, x, v = tr.times, tr.states[:, 0], tr.states[:, 3]
    cuts = [0.0, *[e.t for e in tr.events], t[-1]]
    rows = []
    for ta, tb in zip(cuts[:-1], cuts[1:]):
        idx = np.flatnonzero((t > ta + 1.5 * sample_dt) & (t < tb - 1.5 * sample_dt))
        if len(idx) < 12:
            continue
        mid = x[idx[len(idx) // 2]]
        under = np.flatnonzero((s > mid + lo) & (s < mid + hi))
        N0, N1 = (beam_forces(s[under], xx, weight) for xx in (mid, mid + 1e-3))
        contact = under[N0 > 0]
        f0, f1 = mu * drive[under] @ N0, mu * drive[under] @ N1  # eqs. 22 / 33 at two positions of one set
        k = -(f1 - f0) / 1e-3
        k = 0.0 if abs(k) < 1e-9 * weight / cells.pitch else k  # all wheels one way: a constant force, no spring
        centre = mid + f0 / k if k else float("nan")
        # the engine's trajectory: a = alpha x + beta + gamma v fitted by least squares, a by central differences
        a = (v[idx + 1] - v[idx - 1]) / (t[idx + 1] - t[idx - 1])
        (alpha, beta, gamma), *_ = np.linalg.lstsq(np.column_stack([x[idx], np.ones(len(idx)), v[idx]]), a,
                                                   rcond=None)
        # and the closed form from the stretch's first sample, for the largest deviation
        i0 = idx[0]
        A = np.array([[0.0, 1.0, 0.0], [-k / mass, -damping / mass, (f0 + k * mid) / mass], [0.0, 0.0, 0.0]])
        gaps = np.diff(t[idx])
        flow = expm(A * gaps.mean())  # the exact flow over one sample spacing (the samples are evenly spaced)
        state, closed = np.array([x[i0], v[i0], 1.0]), np.empty(len(idx))
        for j in range(len(idx)):
            closed[j] = state[0]
            if j + 1 < len(idx):
                state = (flow if abs(gaps[j] - gaps.mean()) < 1e-12 else expm(A * gaps[j])) @ state
        rows.append({"t_start": float(ta), "t_end": float(tb), "cells": " ".join(map(str, under.tolist())),
                     "contact": " ".join(map(str, contact.tolist())), "k_closed": float(k),
                     "k_engine": float(-alpha * mass), "centre_closed": float(centre),
                     "centre_engine": float(-beta / alpha) if abs(alpha) > 1e-9 else float("nan"),
                     "omega_closed": float(np.sqrt(k / mass)) if k > 0 else float("nan"),
                     "damping_closed": float(damping), "damping_engine": float(-gamma * mass),
                     "max_deviation": float(np.max(np.abs(closed - x[idx]))), "samples": len(idx)})
    return rows, tr, setup


def row_oscillator(out: Path) -> Result:
    """The 1-D end-reversed row (bundled scenarios ``row_oscillator``, Coulomb, and ``row_oscillator_viscous``):
    between support changes a simple (Coulomb) or damped (viscous) harmonic oscillator whose stiffness and centre
    come from the contact set alone; they change when the supports change."""
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = new_figure(2, 1, 10, 6.4)
    table: dict[str, list] = {}
    numbers: dict = {}
    ok = True
    for row, (scenario, label) in enumerate((("row_oscillator", "Coulomb"), ("row_oscillator_viscous", "viscous"))):
        rows, tr, setup = row_segments(scenario)
        spring = 1e-6 * setup.specs[0].weight(setup.scenario.gravity) / setup.cells.pitch  # N/m: below, no spring
        osc = [r for r in rows if r["k_closed"] > spring]
        rel_k = max(abs(r["k_engine"] / r["k_closed"] - 1) for r in osc)
        d_centre = max(abs(r["centre_engine"] - r["centre_closed"]) for r in osc)
        dev = max(r["max_deviation"] for r in rows)
        distinct = len({(round(r["k_closed"], 6), round(r["centre_closed"], 6)) for r in osc})
        d_damp = max(abs(r["damping_engine"] - r["damping_closed"]) for r in rows) / setup.specs[0].weight(
            setup.scenario.gravity)
        numbers[label] = {"stretches": len(rows), "oscillating_stretches": len(osc), "distinct_oscillators": distinct,
                          "stiffness_rel_error": rel_k, "centre_error_m": d_centre, "max_deviation_m": dev,
                          "damping_error_over_weight_s_per_m": d_damp,
                          "frequencies_rad_per_s": sorted({round(r["omega_closed"], 6) for r in osc})}
        ok &= rel_k < 1e-3 and d_centre < 1e-5 and dev < 1e-7 and distinct >= 2 and d_damp < 1e-3
        for r in rows:
            table.setdefault("law", []).append(label)
            for key, value in r.items():
                table.setdefault(key, []).append(value)
        a = ax[row, 0]
        t, x = tr.times, tr.states[:, 0]
        a.plot(t, x, color="tab:blue", lw=1.6, label="engine")
        for i, r in enumerate(osc):
            a.hlines(r["centre_closed"], r["t_start"], r["t_end"], color="k", ls="--", lw=1,
                     label="closed-form centre of the contact set" if i == 0 else None)
        for e in tr.events:
            a.axvline(e.t, color="0.8", lw=0.6, zorder=0)
        a.set_ylabel("x (m)")
        omegas = ", ".join(f"{w:.3g}" for w in numbers[label]["frequencies_rad_per_s"])
        a.set_title(f"{label} ({scenario}): {len(rows)} support sets (grey lines: changes), {distinct} oscillators "
                    f"(omega = {omegas} rad/s)\nengine within {dev:.1g} m of the closed form", fontsize=9)
        a.legend(fontsize=8, loc="lower right")
    ax[1, 0].set_xlabel("t (s)")
    figure = save_figure(fig, out / "row_oscillator.png")
    units = {"law": "", "t_start": "s", "t_end": "s", "cells": "", "contact": "", "k_closed": "N/m",
             "k_engine": "N/m", "centre_closed": "m", "centre_engine": "m", "omega_closed": "rad/s",
             "damping_closed": "N s/m", "damping_engine": "N s/m", "max_deviation": "m", "samples": ""}
    path = write_table(out / "row_oscillator.csv", {k: (v, units[k]) for k, v in table.items()})
    c, v = numbers["Coulomb"], numbers["viscous"]
    return Result(
        "row_oscillator", "The end-reversed row: a harmonic oscillator that changes with the supports",
        f"{SEED}, Section 2, recalling its ref. 13 (J. Luntz, W. Messner, H. Choset, \"Parcel manipulation and "
        "dynamics with a distributed actuator array: the virtual vehicle\", Proc. IEEE ICRA 1997)",
        "\"Using both friction laws, the resulting parcel dynamics are that of a simple or damped harmonic "
        "oscillator, where the frequency, center of oscillation, and damping constant are constants which change as "
        "the parcel shifts from one set of supports to another.\"",
        f"Coulomb: {c['distinct_oscillators']} oscillators, stiffness within {c['stiffness_rel_error']:.1g}, centre "
        f"within {c['centre_error_m']:.1g} m, path within {c['max_deviation_m']:.1g} m; viscous: "
        f"{v['distinct_oscillators']} oscillators, damping mu W within {v['damping_error_over_weight_s_per_m']:.1g} "
        f"W s/m, path within {v['max_deviation_m']:.1g} m",
        bool(ok), "per support set: stiffness to 1e-3, centre to 1e-5 m, damping to 1e-3 W s/m (fitted to the "
        "engine's samples), path to 1e-7 m of the closed form; at least two different oscillators per law",
        numbers, [figure, path])
