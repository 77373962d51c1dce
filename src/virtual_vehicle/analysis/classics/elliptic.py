"""Elliptic fields (Kavraki 1997): the field ``f(x, y) = -(k1 x, k2 y)``, k1 != k2, gives most parts exactly two
stable equilibrium orientations, pi apart.

Here the field is a wheel-velocity field on a fine array of cells, ``V_i = -(k1 x_i, k2 y_i)`` (m/s), under the
viscous law, whose force on a parcel at rest is ``mu V_i N_i`` per cell (eq. 30): the elliptic field sampled at the
cells and weighted by their normal forces. The package's :func:`~virtual_vehicle.analysis.equilibria.equilibria`
finds the equilibria. Beside it, the continuous prediction: a uniform plate's potential ``integral of (k1 x^2 + k2
y^2) / 2`` is least when its axis of least second moment lies along the weaker pull (y when k1 > k2), at two
headings pi apart; a part whose second-moment tensor is isotropic (a square, a regular polygon) has no preferred
heading, so it is not among "most parts".

Units: SI (m, rad, 1/s for k1 and k2), degrees where a name ends in ``_deg``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virtual_vehicle.analysis.classics.base import Result, new_figure, save_figure, write_table
from virtual_vehicle.analysis.classics.squeeze import random_polygon
from virtual_vehicle.analysis.equilibria import equilibria
from virtual_vehicle.model import layout
from virtual_vehicle.model.parcel import ParcelSpec
from virtual_vehicle.physics.laws import LAWS

SOURCE = ("L. E. Kavraki, \"Part orientation with programmable vector fields: two stable equilibria for most "
          "parts\", Proc. IEEE ICRA 1997 (ref. 10 of the seed paper)")

K = (1.0, 0.5)
"""The field's gains k1, k2 along x and y, 1/s (wheel speed per metre from the centre)."""


def elliptic_array(radius: float, pitch: float, gains=K) -> tuple:
    """A square array (``pitch`` m) around the origin wide enough for a part of ``radius`` (m) centred there, and
    the elliptic field's velocities on it (m/s)."""
    n = int(np.ceil(1.5 * radius / pitch)) * 2 + 1
    cells = layout.grid(n, n, pitch, origin=(-(n - 1) * pitch / 2, -(n - 1) * pitch / 2))
    return cells, -cells.positions * np.asarray(gains, dtype=float)


def stable_orientations(spec: ParcelSpec, pitch: float, headings: int = 73, gains=K) -> list[float]:
    """Headings (rad, [0, 2 pi)) of the stable equilibria the package finds for ``spec`` in the elliptic field on
    an array of ``pitch`` (m), its centre of mass searched within half a pitch of the field's centre."""
    cells, velocities = elliptic_array(spec.radius, pitch, gains)
    h = pitch / 2
    eqs = equilibria(cells, spec, velocities, LAWS["viscous"], bounds=(-h, -h, h, h), step=h,
                     headings=np.linspace(0.0, 2 * np.pi, headings))
    return sorted(e.pose[2] for e in eqs if e.stable and e.rotation == "stable")


def continuous_orientation(spec: ParcelSpec, gains=K) -> float:
    """The continuous theory's stable heading (rad, modulo pi) of a uniform plate: its axis of least second moment
    along the weaker pull."""
    v = spec.footprint
    x, y = v[:, 0], v[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    ixx = np.sum((x * x + x * xn + xn * xn) * cross) / 12  # second moments of the outline about its centroid
    iyy = np.sum((y * y + y * yn + yn * yn) * cross) / 12
    ixy = np.sum((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * cross) / 24
    axis = 0.5 * np.arctan2(2 * ixy, ixx - iyy)  # direction of the largest spread (least second moment about it)
    weak = np.pi / 2 if gains[0] > gains[1] else 0.0
    return float((weak - axis) % np.pi)


def _gap(a: float, b: float) -> float:
    return abs((a - b + np.pi / 2) % np.pi - np.pi / 2)


def elliptic_fields(out: Path, parts: int = 30, pitch: float = 0.005, radius: float = 0.08, seed: int = 1997,
                    controls: bool = True) -> Result:
    """Over ``parts`` random polygons (``radius`` m, cells ``pitch`` m apart): the fraction with exactly two stable
    orientations, and their headings against the continuous prediction; with ``controls``, a square and a regular
    hexagon (isotropic: the theory's exceptions) beside them."""
    rng = np.random.default_rng(seed)
    specs = [random_polygon(rng, radius) for _ in range(parts)]
    found = [stable_orientations(s, pitch) for s in specs]
    predicted = [continuous_orientation(s) for s in specs]
    two = [len(f) == 2 and _gap(f[0], f[1]) < np.radians(3) and abs(abs(f[1] - f[0]) - np.pi) < np.radians(3)
           for f in found]
    errors = [max((_gap(h, p) for h in f), default=np.nan) for f, p in zip(found, predicted)]
    fraction = sum(two) / parts
    worst = max((e for e, ok in zip(errors, two) if ok), default=np.nan)
    control_counts = {}
    if controls:
        from virtual_vehicle.model.parcel import polygon, rectangle

        side = 1.4 * radius
        hexagon = [[radius * np.cos(a), radius * np.sin(a)] for a in np.arange(6) * np.pi / 3 + 0.1]
        for name, spec in (("square", rectangle(side, side, 1.0, 0.5)), ("hexagon", polygon(hexagon, 1.0, 0.5))):
            control_counts[name] = len(stable_orientations(spec, pitch))
    out.mkdir(parents=True, exist_ok=True)
    table = write_table(out / "elliptic.csv", {
        "part": (list(range(parts)), ""), "vertices": ([len(s.footprint) for s in specs], ""),
        "stable_count": ([len(f) for f in found], ""), "exactly_two": (two, ""),
        "stable_deg": ([" ".join(f"{np.degrees(h):.3f}" for h in f) for f in found], "deg"),
        "continuous_deg": (np.degrees(predicted), "deg"), "worst_error_deg": (np.degrees(errors), "deg")})
    figure = _figure(out / "elliptic.png", specs, found, predicted, two, pitch, control_counts)
    numbers = {"parts": parts, "pitch_m": pitch, "radius_m": radius, "gains_per_s": list(K),
               "exactly_two": int(sum(two)), "fraction_exactly_two": fraction,
               "stable_counts": [len(f) for f in found], "worst_error_to_continuous_deg": float(np.degrees(worst)),
               "control_stable_counts": control_counts}
    controls_text = (", ".join(f"{k}: {v} stable" for k, v in control_counts.items()) + " (isotropic controls)"
                     if control_counts else "")
    passed = bool(fraction > 0.5 and worst < np.radians(3) and all(v != 2 for v in control_counts.values()))
    return Result(
        "elliptic", "Elliptic fields: two stable orientations for most parts", SOURCE,
        "Paraphrase (the paper's text is not held here; its title states it): an elliptic field f(x, y) = -(k1 x, "
        "k2 y), k1 != k2, gives most parts exactly two stable equilibrium orientations (pi apart)",
        f"{sum(two)}/{parts} random polygons ({100 * fraction:.0f} %) have exactly two stable orientations pi apart, "
        f"within {np.degrees(worst):.2f} deg of the continuous prediction (cells {1e3 * pitch:g} mm, parts of "
        f"{1e3 * radius:g} mm radius, k = {K[0]:g}, {K[1]:g} 1/s)" + (f"; {controls_text}" if controls_text else ""),
        passed, "a majority (\"most parts\") with exactly two, pi apart to 3 deg, each within 3 deg of the continuous "
        "prediction; the isotropic controls must not show exactly two", numbers, [figure, table])


def _figure(path: Path, specs, found, predicted, two, pitch, controls) -> Path:
    fig, ax = new_figure(1, 2, 11, 4.3)
    a = ax[0, 0]
    counts = [len(f) for f in found]
    bins = np.arange(0, max(counts + [4]) + 2) - 0.5
    a.hist(counts, bins=bins, color="tab:blue", rwidth=0.8)
    a.set_xlabel("stable orientations found in [0, 360) deg")
    a.set_ylabel("parts")
    shown = "; ".join(f"{k}: {v}" for k, v in controls.items())
    a.set_title(f"{sum(two)} of {len(specs)} random polygons: exactly two (cells {1e3 * pitch:g} mm)"
                + (f"\nisotropic controls (not counted): {shown}" if shown else ""), fontsize=9)
    a = ax[0, 1]
    for f, p in zip(found, predicted):
        for h in f:
            a.plot(np.degrees(p), np.degrees(h % np.pi), "o", color="tab:blue", mfc="none")
    a.plot([0, 180], [0, 180], "k--", lw=0.8, label="equal")
    a.set_xlabel("continuous prediction, modulo 180 (deg)")
    a.set_ylabel("package's stable headings, modulo 180 (deg)")
    a.set_title("each stable heading against the continuous theory", fontsize=9)
    a.legend(fontsize=8)
    return save_figure(fig, path)
