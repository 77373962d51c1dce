"""Discreteness destabilises orientation (Luntz, Messner, Choset, IJRR 2001): a field designed on the continuous
model to position and orient a part stably positions it on a discrete array too, but orients it poorly; closing the
loop on the cells' own sensors restores the orientation.

The open-loop field is the inversion of the continuous dynamics: the linear field ``V(p) = -K (p - x_t)`` (m/s),
``K = R(phi) diag(k1, k2) R(phi)^T`` (1/s). Under the viscous law a parcel at rest feels ``f = mu sum N_i V_i`` and
``tau = mu sum N_i r_i x V_i`` (eqs. 30, 34, r_i from the centre of mass). Because the normal forces balance the
weight and its moment whatever the supports (eqs. 4-5: ``sum N_i = W``, ``sum N_i r_i = 0``), the force is exactly
``-mu W K (x_c - x_t)`` on any array: the translation is linear, continuous and stable at the target. The torque,
``-mu (K_xy (S_xx - S_yy) + (K_yy - K_xx) S_xy)`` with ``S = sum N_i r_i r_i^T``, depends on the normal forces'
second moment. On a continuous array the pressure is uniform over the footprint, ``S`` is ``W / A`` times the part's
area second moment, and the torque turns the part's axis of least second moment to the weaker gain's direction (as
in :mod:`~virtual_vehicle.analysis.classics.elliptic`): ``phi`` is chosen so that this stable heading is the target
heading. On a discrete array ``S`` is that of the few supporting cells, constant while the supports do not change:
the torque at the target position is piecewise constant in the heading, and the part stops where a cell entering or
leaving the footprint flips its sign, not at the target.

Units: SI (m, s, rad, N, N m, 1/s), mm and degrees where a name says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import shapely

from virtual_vehicle.analysis.classics.base import Result, new_figure, save_figure, write_table
from virtual_vehicle.analysis.classics.elliptic import continuous_orientation
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.errors import TippingError
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import ParcelSpec, polygon, rectangle
from virtual_vehicle.physics.laws import LAWS

SOURCE = ("J. Luntz, W. Messner, H. Choset, \"Distributed manipulation using discrete actuator arrays\", "
          "International Journal of Robotics Research 20(7), 553-583, 2001")

GAINS = (4.0, 2.0)
"""The open-loop field's gains k1, k2 (1/s, wheel speed per metre from the target) along its principal axes."""
PITCH = 0.05
"""Cell pitch of the discrete array (m), as in the bundled pose scenarios (the authors' cells are of this order)."""
MU = 0.8
"""Viscous coefficient of the parts (s/m)."""
TOLERANCE_DEG = 1.5
"""A target heading counts as held open loop when a stable heading of the discrete torque lies within this (deg)."""


def design_field(positions: np.ndarray, spec: ParcelSpec, target, gains=GAINS) -> np.ndarray:
    """The open-loop field (m/s at each of ``positions``, (n, 2) m) that positions ``spec`` at ``target`` = (x, y,
    theta) and, on a continuous array, orients it there: the linear field turned so that the part's axis of least
    second moment lies along the weaker gain at the target heading."""
    phi = float(target[2]) - continuous_orientation(spec, gains)
    c, s = np.cos(phi), np.sin(phi)
    rot = np.array([[c, -s], [s, c]])
    K = rot @ np.diag(gains) @ rot.T
    return -(np.asarray(positions, dtype=float) - np.asarray(target[:2], dtype=float)) @ K.T


def torque_curve(cells, spec: ParcelSpec, velocities: np.ndarray, target, headings) -> np.ndarray:
    """(len(headings), 3) force (N, N) and torque (N m) on the part at rest with its centre of mass at the target
    position and each heading of ``headings`` (rad), read from the engine's piece (eqs. 30, 34)."""
    model = ParcelModel(cells, spec, velocities, LAWS["viscous"])
    out = np.empty((len(headings), 3))
    for i, th in enumerate(headings):
        y = np.array([target[0], target[1], th, 0.0, 0.0, 0.0])
        acc = model.piece_at(y).rhs(0.0, y)
        out[i] = acc[3] * spec.mass, acc[4] * spec.mass, acc[5] * spec.inertia
    return out


def stable_offsets(offsets: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """Heading offsets (rad) from the target where the ``torque`` sampled over one period [-pi/2, pi/2) of the
    field falls through zero as the heading increases (a stable rotational equilibrium; on a jump of the torque, a
    sliding one), by linear interpolation; the last sample wraps to the first."""
    out = []
    ext = np.append(offsets, offsets[0] + np.pi)
    tq = np.append(torque, torque[0])
    for i in range(len(offsets)):
        a, b = tq[i], tq[i + 1]
        if a > 0 >= b:
            out.append(float(_wrap(ext[i] + (ext[i + 1] - ext[i]) * a / (a - b))))
    return np.array(out)


def array_around(target, radius: float, pitch: float):
    """A square grid of ``pitch`` (m) centred on the target's position with room for a part of ``radius`` (m) and
    a margin of travel; the target sits at the centre of a square of four cells."""
    n = 2 * int(np.ceil((radius + 0.1) / pitch)) + 2
    origin = (target[0] - (n - 1) * pitch / 2, target[1] - (n - 1) * pitch / 2)
    return layout.grid(n, n, pitch, origin=origin)


def family(parts: int, seed: int = 2001, mass: float = 1.0) -> list[ParcelSpec]:
    """``parts`` parts of several sizes and shapes, alternately rectangles (0.14 to 0.3 m long, aspect 0.45 to 0.8, at
    least 0.09 m wide)
    and random convex-ish polygons (5 to 8 vertices at 0.7 to 1 times a radius of 0.1 to 0.18 m, the centre of mass
    at least 0.06 m from the outline, so that none is so thin that it tips between the 5 cm cells), each a uniform
    plate (viscous coefficient :data:`MU`)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(parts):
        if k % 2 == 0:
            length = rng.uniform(0.14, 0.3)
            width = max(0.09, length * rng.uniform(0.45, 0.8))
            out.append(rectangle(length, width, mass, MU, name=f"part{k}"))
            continue
        while True:
            n, radius = int(rng.integers(5, 9)), rng.uniform(0.1, 0.18)
            angles = np.sort(rng.uniform(0, 2 * np.pi, n))
            radii = rng.uniform(0.7, 1.0, n) * radius
            try:
                spec = polygon(np.column_stack([radii * np.cos(angles), radii * np.sin(angles)]), mass, MU,
                               name=f"part{k}")
            except ValueError:  # not simple, or its centroid outside it: draw again
                continue
            if spec.polygon.exterior.distance(shapely.Point(0.0, 0.0)) >= 0.06:  # a sliver tips between cells
                out.append(spec)
                break
    return out


def _wrap(a):
    """Heading difference wrapped modulo pi (the field's symmetry) into [-pi/2, pi/2), rad."""
    return (np.asarray(a) + np.pi / 2) % np.pi - np.pi / 2


def open_loop(spec: ParcelSpec, target, start, pitch: float = PITCH, duration: float = 4.0):
    """Simulate the part from rest at ``start`` (x, y, theta) in the open-loop field for ``target`` on an array of
    ``pitch`` (m); returns the trajectory."""
    cells = array_around(target, spec.radius, pitch)
    model = ParcelModel(cells, spec, design_field(cells.positions, spec, target), LAWS["viscous"])
    return integrate(model, np.array([*start, 0.0, 0.0, 0.0], dtype=float), 0.0, duration, sample_dt=0.02)


def analyse_part(spec: ParcelSpec, target, pitch: float, step_deg: float = 0.25) -> dict:
    """The torque on ``spec`` at rest at the target position on cells ``pitch`` (m) apart, over headings target -90
    to +90 deg (the field's period, sampled every ``step_deg``): the stable offsets (rad), the nearest one to the
    target (rad; nan when none) and the largest force there (N; zero up to rounding, eqs. 4-5)."""
    cells = array_around(target, spec.radius, pitch)
    v = design_field(cells.positions, spec, target)
    offsets = np.radians(np.arange(-90.0, 90.0 - step_deg / 2, step_deg))
    ft = torque_curve(cells, spec, v, target, target[2] + offsets)
    stable = stable_offsets(offsets, ft[:, 2])
    nearest = float(stable[np.argmin(np.abs(stable))]) if len(stable) else float("nan")
    return {"offsets": offsets, "torque": ft[:, 2], "stable": stable, "nearest": nearest,
            "max_force": float(np.max(np.hypot(ft[:, 0], ft[:, 1])))}


def closed_loop(specs: list[ParcelSpec], offset, pitch: float = PITCH, duration: float = 6.0,
                spacing: float = 0.6, central: bool = False) -> tuple[list, list, object]:
    """All ``specs`` at once, each in its own square of ``spacing`` (m) on one array of ``pitch`` (m), driven by
    the bundled pose program (the cells' own phototransistors, five per cell; by the cells under each part, or with
    ``central`` one computer) from its target displaced by ``offset`` = (dx, dy, dtheta) to the target. Returns the
    targets, the starts (x, y, theta) and the run's result."""
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.sim import run

    cols = int(np.ceil(np.sqrt(len(specs))))
    rows = int(np.ceil(len(specs) / cols))
    slots = int(round(spacing / pitch))
    targets, starts, parcels = [], [], []
    for k, spec in enumerate(specs):
        i, j = k % cols, k // cols
        # each target at the centre of a square of four cells, as in the open-loop runs
        t = ((i + 0.5) * spacing - pitch / 2, (j + 0.5) * spacing - pitch / 2, 0.3)
        s = (t[0] + offset[0], t[1] + offset[1], t[2] + offset[2])
        targets.append(t)
        starts.append(s)
        parcels.append({"name": spec.name, "vertices": spec.footprint.tolist(), "mass": spec.mass, "mu": spec.mu,
                        "inertia": spec.inertia, "x": s[0], "y": s[1], "theta": s[2]})
    data = {"name": "orientation_closed_loop", "duration": duration, "output_dt": 0.02,
            "array": {"kind": "grid", "nx": cols * slots, "ny": rows * slots, "pitch": pitch},
            "control": {"program": "pose", "central": central, "period": 0.02, "speed": 0.2, "gain": 3.0,
                        "targets": [list(t) for t in targets]},
            "friction": {"law": "viscous"}, "parcels": parcels}
    return targets, starts, run(parse_scenario(data).build())


def discreteness_orientation(out: Path, parts: int = 16, seed: int = 2001, fine_pitch: float = 0.005) -> Result:
    """Over a family of ``parts`` parts (:func:`family`): the open-loop field's stable headings at the target on the
    discrete array (5 cm cells) and on a fine one (``fine_pitch`` m, standing for the continuous array); the pose
    reached open loop and closed loop (the pose program on the cells' own sensors) from the target displaced by
    (-60 mm, +40 mm, +-12 deg)."""
    specs = family(parts, seed)
    target = (0.5 - PITCH / 2, 0.5 - PITCH / 2, 0.3)
    tol = np.radians(TOLERANCE_DEG)
    offsets = [(-0.06, 0.04, np.radians(12.0)), (-0.06, 0.04, np.radians(-12.0))]
    coarse = [analyse_part(s, target, PITCH) for s in specs]
    fine = [analyse_part(s, target, fine_pitch, step_deg=0.5) for s in specs]
    opened = np.full((parts, 2, 2), np.nan)  # part, start, (position error m, heading error rad)
    closed = np.full((parts, 2, 2), np.nan)
    statuses = [[""] * 2 for _ in range(parts)]
    for j, off in enumerate(offsets):
        for k, spec in enumerate(specs):
            tr = open_loop(spec, target, (target[0] + off[0], target[1] + off[1], target[2] + off[2]))
            e = tr.states[-1]
            opened[k, j] = np.hypot(e[0] - target[0], e[1] - target[1]), abs(_wrap(e[2] - target[2]))
            statuses[k][j] = tr.status
        targets, _, res = closed_loop(specs, off)
        for k, (pr, t) in enumerate(zip(res.parcels, targets)):
            e = pr.trajectory.states[-1]
            closed[k, j] = np.hypot(e[0] - t[0], e[1] - t[1]), abs(_wrap(e[2] - t[2]))
            statuses[k][j] += "/" + pr.trajectory.status
    ok = np.array([all(s == "completed/completed" for s in row) for row in statuses])
    near_c = np.array([abs(c["nearest"]) if np.isfinite(c["nearest"]) else np.inf for c in coarse])
    near_f = np.array([abs(f["nearest"]) if np.isfinite(f["nearest"]) else np.inf for f in fine])
    unstable = near_c > tol  # the target heading is no stable rotational equilibrium of the discrete array
    worst_open, worst_closed = opened.max(axis=1), closed.max(axis=1)  # over the two starts
    n = {"parts": parts, "parts_not_tipping": int(ok.sum()), "pitch_m": PITCH, "fine_pitch_m": fine_pitch,
         "gains_per_s": list(GAINS), "tolerance_deg": TOLERANCE_DEG,
         "fraction_target_unstable_discrete": float(np.mean(unstable)),
         "fraction_target_unstable_fine": float(np.mean(near_f > tol)),
         "stable_headings_discrete_mean": float(np.mean([len(c["stable"]) for c in coarse])),
         "stable_headings_fine_mean": float(np.mean([len(f["stable"]) for f in fine])),
         "nearest_stable_fine_max_deg": float(np.degrees(near_f.max())),
         "max_force_at_target_N": float(max(c["max_force"] for c in coarse))}
    for name, worst in (("open", worst_open[ok]), ("closed", worst_closed[ok])):
        n[f"{name}_position_mean_mm"] = float(1e3 * worst[:, 0].mean())
        n[f"{name}_position_max_mm"] = float(1e3 * worst[:, 0].max())
        n[f"{name}_heading_mean_deg"] = float(np.degrees(worst[:, 1].mean()))
        n[f"{name}_heading_max_deg"] = float(np.degrees(worst[:, 1].max()))
    out.mkdir(parents=True, exist_ok=True)
    table = write_table(out / "orientation.csv", {
        "part": ([s.name for s in specs], ""), "vertices": ([len(s.footprint) for s in specs], ""),
        "radius": ([s.radius for s in specs], "m"),
        "stable_count_discrete": ([len(c["stable"]) for c in coarse], ""),
        "nearest_stable_discrete_deg": ([float(np.degrees(c["nearest"])) for c in coarse], "deg"),
        "stable_count_fine": ([len(f["stable"]) for f in fine], ""),
        "nearest_stable_fine_deg": ([float(np.degrees(f["nearest"])) for f in fine], "deg"),
        "target_unstable_discrete": ([bool(u) for u in unstable], ""),
        "open_position_mm": (1e3 * worst_open[:, 0], "mm"), "open_heading_deg": (np.degrees(worst_open[:, 1]), "deg"),
        "closed_position_mm": (1e3 * worst_closed[:, 0], "mm"),
        "closed_heading_deg": (np.degrees(worst_closed[:, 1]), "deg"),
        "status_plus12": ([r[0] for r in statuses], ""), "status_minus12": ([r[1] for r in statuses], "")})
    figure = _figure(out / "orientation.png", specs, coarse, fine, worst_open, worst_closed, ok, n)
    passed = bool(ok.all() and n["fraction_target_unstable_discrete"] >= 0.25
                  and n["fraction_target_unstable_fine"] == 0.0 and n["open_position_max_mm"] < 0.1
                  and n["closed_heading_mean_deg"] < 0.5 * n["open_heading_mean_deg"]
                  and n["closed_heading_max_deg"] < n["open_heading_max_deg"])
    return Result(
        "orientation", "Discreteness destabilises orientation; closing the loop on the sensors restores it", SOURCE,
        "Paraphrase of the abstract (the paper's text is not held here): inverting the piecewise dynamics gives a "
        "continuous open-loop field that would stably position and orient any object on a continuous array, but "
        "on a discrete array many objects get unstable rotational equilibria, so open loop orients poorly; closed "
        "loop control restores the precision",
        f"the target heading is a stable equilibrium on 5 mm cells for all {parts} parts (within "
        f"{n['nearest_stable_fine_max_deg']:.2f} deg) but not on 5 cm cells for "
        f"{100 * n['fraction_target_unstable_discrete']:.0f} %; open loop: position within "
        f"{n['open_position_max_mm']:.1g} mm, heading {n['open_heading_mean_deg']:.1f} deg mean, "
        f"{n['open_heading_max_deg']:.1f} max; closed loop (pose program): {n['closed_position_mean_mm']:.1f} mm "
        f"mean ({n['closed_position_max_mm']:.1f} max), heading {n['closed_heading_mean_deg']:.1f} deg mean "
        f"({n['closed_heading_max_deg']:.1f} max)",
        passed, f"no part tips; the target unstable (no stable heading within {TOLERANCE_DEG:g} deg) for at least a "
        "quarter of the parts on the discrete array and for none on the fine one; open loop positions within 0.1 "
        "mm; closed loop halves the mean heading error and lowers the largest", n, [figure, table])


def _figure(path: Path, specs, coarse, fine, worst_open, worst_closed, ok, n) -> Path:
    fig, ax = new_figure(1, 3, 16, 4.8)
    a = ax[0, 0]
    k = int(np.argmax([abs(c["nearest"]) if np.isfinite(c["nearest"]) else 0 for c in coarse]))
    for curve, label, style in ((coarse[k], f"{1e3 * PITCH:g} mm cells", "-"),
                                (fine[k], f"{1e3 * n['fine_pitch_m']:g} mm cells", "--")):
        t = curve["torque"]
        a.plot(np.degrees(curve["offsets"]), t / np.max(np.abs(t)), style, lw=1.4, label=label)
        a.plot(np.degrees(curve["stable"]), np.zeros(len(curve["stable"])), "o", mfc="none", ms=7,
               color=a.lines[-1].get_color())
    a.axhline(0, color="0.6", lw=0.6)
    a.axvline(0, color="k", lw=0.8, ls=":")
    a.set_xlabel("heading - target (deg)")
    a.set_ylabel("torque at the target position / its largest")
    a.set_title(f"{specs[k].name}, open-loop field: torque at the target position\n(circles: stable headings; "
                "target at 0)", fontsize=9)
    a.legend(fontsize=8)
    a = ax[0, 1]
    x = np.arange(len(specs))
    a.bar(x - 0.2, np.degrees(worst_open[:, 1]), 0.4, color="tab:red", label="open loop (designed field)")
    a.bar(x + 0.2, np.degrees(worst_closed[:, 1]), 0.4, color="tab:blue", label="closed loop (pose program)")
    a.set_xticks(x, [s.name.removeprefix("part") for s in specs], fontsize=8)
    a.set_xlabel("part (even: rectangles, odd: polygons)")
    a.set_ylabel("heading error reached (deg)")
    a.set_ylim(0, 1.3 * np.degrees(np.nanmax([worst_open[:, 1], worst_closed[:, 1]])))  # room for the legend
    a.set_title(f"heading error reached, worse of two starts\n(target unstable on the {1e3 * PITCH:g} mm array for "
                f"{100 * n['fraction_target_unstable_discrete']:.0f} % of the parts)", fontsize=9)
    a.legend(fontsize=8)
    a = ax[0, 2]
    a.bar(x - 0.2, 1e3 * worst_open[:, 0], 0.4, color="tab:red", label="open loop")
    a.bar(x + 0.2, 1e3 * worst_closed[:, 0], 0.4, color="tab:blue", label="closed loop")
    a.set_xticks(x, [s.name.removeprefix("part") for s in specs], fontsize=8)
    a.set_xlabel("part")
    a.set_ylabel("position error reached (mm)")
    a.set_title(f"position error reached (open loop: all below {n['open_position_max_mm']:.0e} mm,\nits force "
                "exactly linear whatever the supports, eqs. 4-5)", fontsize=9)
    a.legend(fontsize=8)
    return save_figure(fig, path)
