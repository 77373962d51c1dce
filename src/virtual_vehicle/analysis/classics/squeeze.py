"""Squeeze fields (Böhringer, Donald, Mihailovich, MacDonald 1994): the stable orientations of a part in a squeeze
field are those where the squeeze line is an area bisector of the part and the two halves' centres of area lie on
one perpendicular to it; a sequence of squeezes at different angles orients a part up to symmetry.

Two independent computations are compared:

- the *bisector construction* of the continuous theory, with shapely: the part at heading theta, the line parallel
  to the squeeze line that halves its area, and the torque of a unit pressure pushing each half toward that line,
  ``(A / 2) (x_lower - x_upper)`` (m^3 per unit pressure: the halves' centroids, A the area);
- the *package's physics*: the squeeze field on a fine array of cells (``model.fields.Squeeze``), the viscous law,
  the parcel at rest. At each heading the force across the line is brought to zero by bisection over the offset
  (the force is piecewise affine and jumps where a cell enters the footprint, so the balance may sit on a jump: a
  sliding equilibrium; its torque is then the mean of the two sides'), and the torque there is read from the
  engine's piece (paper eqs. 29, 38).

A stable orientation is where the torque falls through zero as the heading increases. Both torques repeat every
pi rad (the field is symmetric about its line), so headings are reported in [0, pi).

Units: SI (m, rad, N, N m), degrees where a name ends in ``_deg``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import shapely
from shapely import affinity

from virtual_vehicle.analysis.classics.base import Result, new_figure, save_figure, write_table
from virtual_vehicle.engine.dynamics import ParcelModel, integrate
from virtual_vehicle.model import fields, layout, parcel
from virtual_vehicle.model.parcel import ParcelSpec
from virtual_vehicle.physics.laws import LAWS

SOURCE = ("K.-F. Böhringer, B. R. Donald, R. Mihailovich, N. C. MacDonald, \"A theory of manipulation and control "
          "for microfabricated actuator arrays\", Proc. IEEE ICRA 1994 (ref. 9 of the seed paper)")

SPEED = 0.2
"""Squeeze speed of the wheels toward the line, m/s."""


def random_polygon(rng: np.random.Generator, radius: float, mass: float = 1.0, mu: float = 0.5) -> ParcelSpec:
    """A random polygon of 4 to 8 vertices at 0.4 to 1 times ``radius`` (m) from a centre, in the order of their
    angles about it, as a uniform plate of ``mass`` kg (viscous coefficient ``mu``, s/m). A draw whose outline is
    not simple or whose centroid falls outside it is drawn again."""
    while True:
        k = int(rng.integers(4, 9))
        angles = np.sort(rng.uniform(0, 2 * np.pi, k))
        radii = rng.uniform(0.4, 1.0, k) * radius
        try:
            return parcel.polygon(np.column_stack([radii * np.cos(angles), radii * np.sin(angles)]), mass, mu)
        except ValueError:
            continue


def bisector_torque(outline, theta: float) -> tuple[float, float]:
    """The bisector construction for the part ``outline`` ((k, 2) m about its centroid) turned by ``theta`` (rad) in
    a squeeze along the x axis: (offset c of the area-bisecting line y = c, m; torque of a unit pressure pushing
    each half toward that line, m^3, counter-clockwise positive)."""
    part = affinity.rotate(shapely.Polygon(outline), theta, origin=(0, 0), use_radians=True)
    x0, y0, x1, y1 = part.bounds
    lo, hi = y0, y1
    for _ in range(60):  # to well below a micrometre
        c = 0.5 * (lo + hi)
        if part.intersection(shapely.box(x0 - 1, y0 - 1, x1 + 1, c)).area < part.area / 2:
            lo = c
        else:
            hi = c
    c = 0.5 * (lo + hi)
    lower = part.intersection(shapely.box(x0 - 1, y0 - 1, x1 + 1, c)).centroid
    upper = part.intersection(shapely.box(x0 - 1, c, x1 + 1, y1 + 1)).centroid
    return c, part.area / 2 * (lower.x - upper.x)  # upper half pushed down (-y), lower half up (+y)


def squeeze_array(radius: float, pitch: float) -> tuple:
    """A square array (pitch in m) wide enough for a part of ``radius`` (m) on the squeeze line y = 0 through the
    origin, and the squeeze field's velocities (m/s) there."""
    n = int(np.ceil(3 * radius / pitch)) * 2 + 1
    cells = layout.grid(n, n, pitch, origin=(-(n - 1) * pitch / 2, -(n - 1) * pitch / 2))
    return cells, fields.Squeeze((0.0, 0.0), (1.0, 0.0), SPEED).velocities(cells)


def package_torque(model: ParcelModel, spec: ParcelSpec, theta: float, x: float = 0.0) -> tuple[float, float]:
    """The engine's view at heading ``theta`` (rad), centre of mass at ``x`` (m) along the line: (offset y (m) of
    the centre of mass where the force across the line vanishes, torque there, N m)."""

    def force_torque(y):
        state = np.array([x, y, theta, 0.0, 0.0, 0.0])
        acc = model.piece_at(state).rhs(0.0, state)
        return acc[4] * spec.mass, acc[5] * spec.inertia

    lo, hi = -0.5 * spec.radius, 0.5 * spec.radius
    while force_torque(lo)[0] <= 0 or force_torque(hi)[0] >= 0:
        lo, hi = 1.5 * lo, 1.5 * hi  # the squeeze pushes toward the line: it changes sign within the footprint
        if hi > spec.radius:
            raise ValueError(f"no force balance across the squeeze line at heading {theta} rad")
    while hi - lo > 1e-8:
        mid = 0.5 * (lo + hi)
        if force_torque(mid)[0] > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi), 0.5 * (force_torque(lo)[1] + force_torque(hi)[1])


def stable_headings(headings: np.ndarray, torque: np.ndarray, falling: bool = True) -> np.ndarray:
    """Headings (rad, in [0, pi)) where ``torque`` sampled at ``headings`` (over [0, pi], both ends) falls through
    zero (stable; rises when ``falling`` is False: unstable), by linear interpolation between samples."""
    out = []
    for i in range(len(headings) - 1):
        a, b = torque[i], torque[i + 1]
        if (a > 0 >= b) if falling else (a < 0 <= b):
            out.append(headings[i] + (headings[i + 1] - headings[i]) * a / (a - b))
    return np.unique(np.round(np.mod(out, np.pi), 12))


def _gap(a: float, b: float) -> float:
    """Distance between two headings modulo pi, rad."""
    return abs((a - b + np.pi / 2) % np.pi - np.pi / 2)


def compare_polygon(spec: ParcelSpec, pitch: float, samples: int = 181) -> dict:
    """The bisector construction against the package for one part: both torque curves over [0, pi] and their
    stable and unstable headings (rad)."""
    headings = np.linspace(0.0, np.pi, samples)
    cells, velocities = squeeze_array(spec.radius, pitch)
    model = ParcelModel(cells, spec, velocities, LAWS["viscous"])
    bis = np.array([bisector_torque(spec.footprint, th) for th in headings])
    pkg = np.array([package_torque(model, spec, th) for th in headings])
    return {"headings": headings, "bisector_offset": bis[:, 0], "bisector_torque": bis[:, 1],
            "package_offset": pkg[:, 0], "package_torque": pkg[:, 1],
            "bisector_stable": stable_headings(headings, bis[:, 1]),
            "package_stable": stable_headings(headings, pkg[:, 1]),
            "bisector_unstable": stable_headings(headings, bis[:, 1], falling=False),
            "package_unstable": stable_headings(headings, pkg[:, 1], falling=False)}


def match(reference: np.ndarray, found: np.ndarray) -> float:
    """Largest heading error (rad, modulo pi) from each reference heading to the nearest found one (inf when none
    is found); found headings near no reference ones are counted apart (:func:`extra`)."""
    return max((min((_gap(r, f) for f in found), default=float("inf")) for r in reference), default=0.0)


def extra(reference: np.ndarray, found: np.ndarray) -> int:
    """How many found headings are the nearest to no reference heading (orientations the theory does not have)."""
    nearest = {int(np.argmin([_gap(r, f) for f in found])) for r in reference} if len(found) else set()
    return len(found) - len(nearest)


def squeeze_outcome(phi: float, stable: np.ndarray, unstable: np.ndarray) -> float:
    """Where a part at relative heading ``phi`` (rad) comes to rest in a squeeze whose stable and unstable relative
    headings are given (rad, modulo pi): the stable heading of its basin (between two unstable ones)."""
    bounds = np.sort(np.mod(unstable, np.pi))
    p = phi % np.pi
    lo = bounds[bounds <= p].max() if np.any(bounds <= p) else bounds.max() - np.pi
    hi = bounds[bounds > p].min() if np.any(bounds > p) else bounds.min() + np.pi
    inside = [s for s in np.mod(stable, np.pi) for s in (s - np.pi, s, s + np.pi) if lo < s < hi]
    return float(inside[0] % np.pi)


def two_squeeze_plan(stable: np.ndarray, unstable: np.ndarray, step: float = np.radians(0.5)) -> tuple[float, float]:
    """After a first squeeze (line at 0) the part rests at one of ``stable`` (rad, modulo pi). The angle (rad) of a
    second squeeze line that sends all of them to one orientation, the one with the widest margin to a basin's
    edge, and that margin (rad); (nan, 0) when no angle does."""
    best, margin = float("nan"), 0.0
    for alpha in np.arange(0.0, np.pi, step):
        phis = np.mod(stable - alpha, np.pi)
        ends = {round(squeeze_outcome(p, stable, unstable), 9) for p in phis}
        if len(ends) != 1:
            continue
        room = min(_gap(p, u) for p in phis for u in unstable)
        if room > margin:
            best, margin = float(alpha), float(room)
    return best, margin


def run_plan(spec: ParcelSpec, pitch: float, angles, starts, duration: float = 5.0) -> np.ndarray:
    """Simulate squeezes with lines at ``angles`` (rad) through the origin, one after the other for ``duration``
    seconds each, from rest at the origin with each heading of ``starts`` (rad). Returns (len(starts),
    len(angles)) headings (rad, modulo pi) at the end of each squeeze."""
    cells, _ = squeeze_array(spec.radius, pitch)
    law = LAWS["viscous"]
    models = [ParcelModel(cells, spec, fields.Squeeze((0.0, 0.0), (np.cos(a), np.sin(a)), SPEED).velocities(cells),
                          law) for a in angles]
    out = np.empty((len(starts), len(angles)))
    for i, th in enumerate(starts):
        state = np.array([0.0, 0.0, th, 0.0, 0.0, 0.0])
        for j, model in enumerate(models):
            tr = integrate(model, state, 0.0, duration, sample_dt=duration)
            state = tr.states[-1].copy()
            state[3:] = 0.0  # the next squeeze starts from rest, as a quasi-static plan assumes
            out[i, j] = state[2] % np.pi
    return out


def squeeze_fields(out: Path, parts: int = 8, pitch: float = 0.005, radius: float = 0.08, seed: int = 35,
                   starts: int = 12) -> Result:
    """Stable squeeze orientations of ``parts`` random polygons (``radius`` m, on cells ``pitch`` m apart) from the
    package against the bisector construction; then a two-squeeze plan for the first part with two stable
    orientations, checked by simulating it from ``starts`` headings."""
    rng = np.random.default_rng(seed)
    specs = [random_polygon(rng, radius) for _ in range(parts)]
    rows: dict[str, list] = {}
    curves, errors, offsets = [], [], []
    for k, spec in enumerate(specs):
        c = compare_polygon(spec, pitch)
        curves.append(c)
        errors.append(match(c["bisector_stable"], c["package_stable"]))
        near = [int(np.argmin([_gap(h, s) for h in c["headings"]])) for s in c["bisector_stable"]]
        offsets.append(max(abs(c["package_offset"][i] + c["bisector_offset"][i]) for i in near))
        for s in c["bisector_stable"]:
            f = min(c["package_stable"], key=lambda p: _gap(p, s), default=np.nan)
            rows.setdefault("part", []).append(k)
            rows.setdefault("vertices", []).append(len(spec.footprint))
            rows.setdefault("bisector_stable_deg", []).append(np.degrees(s))
            rows.setdefault("package_stable_deg", []).append(np.degrees(f))
            rows.setdefault("error_deg", []).append(np.degrees(_gap(f, s)) if np.isfinite(f) else np.nan)
            rows.setdefault("bisector_count", []).append(len(c["bisector_stable"]))
            rows.setdefault("package_count", []).append(len(c["package_stable"]))
    # the plan: the first part with two stable orientations modulo pi
    pick = next((k for k, c in enumerate(curves) if len(c["package_stable"]) >= 2), None)
    plan = {}
    if pick is not None:
        c = curves[pick]
        alpha, margin = two_squeeze_plan(c["package_stable"], c["package_unstable"])
        if np.isfinite(alpha):
            begin = np.linspace(0.0, np.pi, starts, endpoint=False) + 0.05
            final = run_plan(specs[pick], pitch, [0.0, alpha], begin)
            predicted = (squeeze_outcome(c["package_stable"][0] - alpha, c["package_stable"], c["package_unstable"])
                         + alpha) % np.pi
            plan = {"part": int(pick), "alpha_rad": alpha, "margin_rad": margin, "starts_rad": begin,
                    "after_first_rad": final[:, 0], "after_second_rad": final[:, 1], "predicted_rad": predicted,
                    "classes_after_first": len(_classes(final[:, 0])), "classes_after_second":
                    len(_classes(final[:, 1])), "spread_after_second_rad": _spread(final[:, 1]),
                    "error_to_predicted_rad": max(_gap(h, predicted) for h in final[:, 1])}
    worst = max(errors)
    worst_offset = max(offsets)
    extras = [extra(c["bisector_stable"], c["package_stable"]) for c in curves]
    counts_agree = int(sum(len(c["bisector_stable"]) == len(c["package_stable"]) for c in curves))
    plan_ok = bool(plan) and plan["classes_after_first"] >= 2 and plan["classes_after_second"] == 1 \
        and plan["error_to_predicted_rad"] < np.radians(3)
    passed = bool(worst < np.radians(3) and plan_ok)
    out.mkdir(parents=True, exist_ok=True)
    units = {"part": "", "vertices": "", "bisector_stable_deg": "deg", "package_stable_deg": "deg", "error_deg": "deg",
             "bisector_count": "", "package_count": ""}
    table = write_table(out / "squeeze.csv", {k: (v, units[k]) for k, v in rows.items()})
    paths = [_figure(out / "squeeze.png", specs, curves, plan, pitch), table]
    if plan:
        paths.append(write_table(out / "squeeze_plan.csv", {
            "start_deg": (np.degrees(plan["starts_rad"]), "deg"),
            "after_first_deg": (np.degrees(plan["after_first_rad"]), "deg"),
            "after_second_deg": (np.degrees(plan["after_second_rad"]), "deg")}))
    numbers = {"parts": parts, "pitch_m": pitch, "radius_m": radius, "counts_agree": counts_agree,
               "extra_stable": extras,
               "worst_heading_error_deg": float(np.degrees(worst)), "worst_offset_error_m": float(worst_offset),
               "plan": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in plan.items()}}
    plan_text = (f"plan for part {plan['part']}: squeeze at 0 then {np.degrees(plan['alpha_rad']):.1f} deg; "
                 f"{starts} simulated starts end in {plan['classes_after_first']} orientations after the first, "
                 f"{plan['classes_after_second']} after the second (spread "
                 f"{np.degrees(plan['spread_after_second_rad']):.2f} deg)") if plan else "no two-squeeze plan found"
    return Result(
        "squeeze", "Squeeze fields: stable orientations at area bisectors; a two-squeeze plan",
        SOURCE,
        "Paraphrase (the paper's text is not held here): a part is in equilibrium in a squeeze field when the "
        "squeeze line bisects its area and the centres of area of the two halves lie on a line perpendicular to "
        "it; stable where the torque turns the part back; squeezes in sequence orient a part up to symmetry",
        f"every bisector orientation of {parts} random polygons found within {np.degrees(worst):.2f} deg, offset "
        f"within {1e3 * worst_offset:.2f} mm (cells {1e3 * pitch:g} mm, parts of {1e3 * radius:g} mm radius); the "
        f"counts agree for {counts_agree}/{parts}: discreteness adds "
        f"{sum(extras)} stable orientations where the torque is shallow; {plan_text}",
        passed, "every stable heading of the bisector construction has one of the package within 3 deg (extra ones "
        "are reported, not failed); the plan "
        "leaves every simulated start within 3 deg of one orientation modulo pi, after at least two after the first",
        numbers, paths)


def _classes(headings: np.ndarray, tol: float = np.radians(3)) -> list[float]:
    """Representatives of the headings (rad) that lie within ``tol`` of each other modulo pi."""
    reps: list[float] = []
    for h in headings:
        if not any(_gap(h, r) < tol for r in reps):
            reps.append(float(h))
    return reps


def _spread(headings: np.ndarray) -> float:
    """Largest distance (rad, modulo pi) between two of the headings."""
    return max((_gap(a, b) for a in headings for b in headings), default=0.0)


def _figure(path: Path, specs, curves, plan, pitch) -> Path:
    fig, ax = new_figure(2, 2, 11, 8.4)
    a = ax[0, 0]
    for k, c in enumerate(curves[:3]):
        deg = np.degrees(c["headings"])
        b, p = c["bisector_torque"], c["package_torque"]
        line, = a.plot(deg, b / np.max(np.abs(b)), lw=2.5, alpha=0.45, label=f"part {k}: bisector construction")
        a.plot(deg, p / np.max(np.abs(p)), color=line.get_color(), lw=1, label=f"part {k}: package")
        a.plot(np.degrees(c["package_stable"]), np.zeros(len(c["package_stable"])), "v", color=line.get_color(),
               ms=8)
    a.axhline(0, color="0.5", lw=0.6)
    a.set_xlabel("heading (deg)")
    a.set_ylabel("torque / its largest value")
    a.set_title(f"torque at the force balance (cells {1e3 * pitch:g} mm); v: stable", fontsize=9)
    a.legend(fontsize=7, ncol=1, loc="lower left")
    a = ax[0, 1]
    for k, c in enumerate(curves):
        for s in c["bisector_stable"]:
            f = min(c["package_stable"], key=lambda p: _gap(p, s), default=np.nan)
            a.plot(np.degrees(s), np.degrees(f), "o", color="tab:blue")
    a.plot([0, 180], [0, 180], "k--", lw=0.8, label="equal")
    a.set_xlabel("stable heading, bisector construction (deg)")
    a.set_ylabel("stable heading, package (deg)")
    more = sum(extra(c["bisector_stable"], c["package_stable"]) for c in curves)
    a.set_title(f"{len(curves)} random polygons: each bisector orientation and the package's nearest\n({more} more "
                "package orientations, from discreteness, not shown)", fontsize=9)
    a.legend(fontsize=8)
    a = ax[1, 0]
    for k, spec in enumerate(specs[:6]):
        fp = np.vstack([spec.footprint, spec.footprint[:1]])
        a.plot(fp[:, 0] + 0.2 * (k % 3), fp[:, 1] - 0.2 * (k // 3), lw=1.5)
        a.text(0.2 * (k % 3), -0.095 - 0.2 * (k // 3), f"part {k}", ha="center", va="top", fontsize=8)
    a.set_ylim(-0.2 * ((min(len(specs), 6) - 1) // 3) - 0.13, 0.1)  # room for the lowest row's names
    a.set_aspect("equal")
    a.set_xlabel("x (m)")
    a.set_ylabel("y (m)")
    a.set_title("the random polygons (heading 0)", fontsize=9)
    a = ax[1, 1]
    if plan:
        start = np.degrees(plan["starts_rad"])
        a.plot(start, np.degrees(plan["after_first_rad"]), "o", mfc="none", label="after squeeze 1 (line at 0 deg)")
        a.plot(start, np.degrees(plan["after_second_rad"]), "x", ms=8,
               label=f"after squeeze 2 (line at {np.degrees(plan['alpha_rad']):.1f} deg)")
        a.axhline(np.degrees(plan["predicted_rad"]), color="k", ls="--", lw=0.8, label="planned (torque curve of the line at 0 deg)")
        a.set_xlabel("start heading (deg)")
        a.set_ylabel("heading modulo 180 (deg)")
        a.set_ylim(0, 180)
        a.set_title(f"two-squeeze plan for part {plan['part']}, simulated by the engine", fontsize=9)
        a.legend(fontsize=8)
    else:
        a.text(0.5, 0.5, "no part with two stable orientations", ha="center", transform=a.transAxes)
    return save_figure(fig, path)
