"""Pictures of a run: the array with each cell's wheel velocity, and the parcels' paths and footprints.

Lengths on the axes are in m.
"""

from __future__ import annotations

import io as _io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon as PolygonPatch  # noqa: E402

from virtual_vehicle.cells.programs import program_of  # noqa: E402
from virtual_vehicle.model.layout import cell_outlines  # noqa: E402
from virtual_vehicle.run.files import write_atomic  # noqa: E402
from virtual_vehicle.run.results import RunResult  # noqa: E402


def plot_paths(result: RunResult, path: str | Path | None = None, title: str | None = None, cell_ids: bool = False):
    """Plot the run: left, the cells (dots; dead cells an X, see :func:`draw_cells`) with their wheel velocities
    (arrows), each parcel's centre-of-mass path and its footprint at the start (dashed), the end (filled; red edge
    and a cross if it tipped) and its target (dotted black, pose control); right, x and y (m) and heading (rad)
    against time (s). ``cell_ids`` writes each cell's id beside it. An array of more than :data:`LARGE_ARRAY` cells
    is drawn as an image with an arrow every few cells. Saves a PNG to ``path`` if given; returns the figure."""
    setup = result.setup
    cells = setup.cells
    P = cells.positions
    fig, (ax, axt) = plt.subplots(1, 2, figsize=(12, 5.2), dpi=110, gridspec_kw={"width_ratios": [1.35, 1]})
    large = draw_cells(ax, setup, cell_ids=cell_ids)
    V = setup.velocities
    speed = np.hypot(V[:, 0], V[:, 1])
    if np.any(speed > 0):
        every = 1
        if large:  # about 40 arrows a side: one every few cells, each as long as those few cells allow
            every = max(1, int(np.ceil(np.sqrt(cells.n) / 40)))
        sel = np.arange(0, cells.n, every)
        if large and cells.shape is not None:  # every few rows and columns of a grid, not every few cells of a row
            rows, cols = cells.shape
            j, i = np.divmod(np.arange(cells.n), cols)
            sel = np.flatnonzero((j % every == 0) & (i % every == 0))
        scale = 0.45 * every * cells.pitch / speed.max()
        note = f", one arrow every {every} cells" if every > 1 else ""
        ax.quiver(P[sel, 0], P[sel, 1], V[sel, 0] * scale, V[sel, 1] * scale, angles="xy", scale_units="xy",
                  scale=1, color="tab:blue", width=0.003, alpha=0.7, zorder=2,
                  label=f"wheel velocity (max {speed.max():.3g} m/s{note})")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    axh = axt.twinx()
    tipped_seen = False
    targets = program_of(setup.scenario.control).markers(setup).targets if setup.scenario.control else None
    for k, pr in enumerate(result.parcels):
        c = colors[(k + 1) % len(colors)]
        tr = pr.trajectory
        ax.plot(tr.states[:, 0], tr.states[:, 1], "-", color=c, lw=1.5, zorder=3, label=f"{pr.spec.name} path")
        if large:  # a parcel is a speck on a large array: mark where it ended
            ax.plot(*tr.states[-1, :2], "o", color=c, ms=5, zorder=4)
        start = pr.spec.world_polygon(tr.states[0])
        end = pr.spec.world_polygon(tr.states[-1])
        ax.add_patch(PolygonPatch(np.asarray(start.exterior.coords), closed=True, fill=False, ls="--", ec=c, lw=1,
                                  label="start (dashed outline)" if k == 0 else None))
        ec = "red" if tr.status == "tipped" else c
        ax.add_patch(PolygonPatch(np.asarray(end.exterior.coords), closed=True, fill=True, fc=c, alpha=0.15, ec=ec,
                                  lw=1.5, label="end (filled)" if k == 0 else None))
        if tr.status == "tipped":
            ax.plot(*tr.states[-1, :2], "x", color="red", ms=9, mew=2, zorder=4,
                    label=None if tipped_seen else "tipped (red edge and cross)")
            tipped_seen = True
        if targets:
            goal = pr.spec.world_polygon(targets[k])
            ax.add_patch(PolygonPatch(np.asarray(goal.exterior.coords), closed=True, fill=False, ls=":", ec="k",
                                      lw=1.2, label="target" if k == 0 else None))
        axt.plot(tr.times, tr.states[:, 0], "-", color=c, lw=1.3, label=f"{pr.spec.name} x")
        axt.plot(tr.times, tr.states[:, 1], "--", color=c, lw=1.3, label=f"{pr.spec.name} y")
        axh.plot(tr.times, tr.states[:, 2], ":", color=c, lw=1.3, label=f"{pr.spec.name} heading")
        for e in tr.events:
            if e.kind == "tip":
                axt.axvline(e.t, color="red", lw=1, alpha=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    sc = setup.scenario
    ax.set_title(title or f"{sc.name}: {sc.friction.law} friction, {sc.duration:g} s")
    ax.autoscale_view()
    ax.margins(0.08)
    legend_below(ax, ncol=3)
    axt.set_xlabel("t (s)")
    axt.set_ylabel("position (m)")
    axh.set_ylabel("heading (rad)")
    lo, hi = axh.get_ylim()
    if hi - lo < 0.02:  # do not magnify rounding noise of a heading that does not change
        mid = 0.5 * (lo + hi)
        axh.set_ylim(mid - 0.1, mid + 0.1)
    axt.set_title("centre of mass and heading")
    lines = axt.get_legend_handles_labels()
    lines2 = axh.get_legend_handles_labels()
    legend_below(axt, lines[0] + lines2[0], lines[1] + lines2[1], ncol=3)
    axt.grid(alpha=0.3)
    return _finish(fig, path)


LARGE_ARRAY = 10_000
"""Cells above which an array is drawn as one image (a pixel per lattice site) instead of a marker per cell."""
MAX_CELL_IDS = 2_000
"""Most cells whose ids :func:`draw_cells` writes (beyond that the labels would be unreadable)."""


def dead_cells(setup, t: float | None = None) -> np.ndarray:
    """(n,) bool: cells dead at time ``t`` (s) of the run of ``setup``: listed or drawn in ``[faults]`` and, from
    their times on, those of ``[[faults.events]]`` (each event's faults are all those of its time, so a cell revived
    by an event is dead no more); ``t`` None: dead at any time of the run."""
    n = setup.cells.n
    faults = setup.faults
    dead = np.zeros(n, bool) if faults is None else np.asarray(faults.dead_cells, bool).copy()
    for te, later in setup.fault_events or ():
        if t is None:
            dead |= np.asarray(later.dead_cells, bool)
        elif te <= t:
            dead = np.asarray(later.dead_cells, bool).copy()
    return dead


def absent_cells(setup, t: float | None = None) -> np.ndarray:
    """(n,) bool: cells not installed at time ``t`` (s) (``[reconfiguration]``: absent at the start, or taken out
    and not yet put back); ``t`` None: out of the array at any time of the run."""
    n = setup.cells.n
    present = np.ones(n, bool) if setup.present is None else np.asarray(setup.present, bool)
    if t is None:
        out = ~present
        for _, now in setup.cell_changes or ():
            out = out | ~np.asarray(now, bool)
        return out
    for tc, now in setup.cell_changes or ():
        if tc <= t:
            present = np.asarray(now, bool)
    return ~present


def cell_raster(cells, values, fill=np.nan) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """One pixel per lattice site for the array's cells (belts left out): (image (rows, columns) of ``values`` (n,),
    ``fill`` where there is no cell; extent (left, right, bottom, top) in m) for ``imshow(origin="lower")``. A
    pixel is a pitch wide and a row spacing tall (hexagonal lattices: odd rows land on the nearest column)."""
    keep = ~cells.belts
    P = cells.positions[keep]
    pitch = cells.pitch
    ys = np.unique(np.round(P[:, 1] / pitch * 1e6) / 1e6 * pitch)
    gaps = np.diff(ys)
    dy = float(gaps[gaps > 1e-9 * pitch].min()) if np.any(gaps > 1e-9 * pitch) else pitch
    x0, y0 = P[:, 0].min(), P[:, 1].min()
    ix = np.round((P[:, 0] - x0) / pitch).astype(np.int64)
    iy = np.round((P[:, 1] - y0) / dy).astype(np.int64)
    img = np.full((iy.max() + 1, ix.max() + 1), fill, dtype=float)
    img[iy, ix] = np.asarray(values, dtype=float)[keep]
    extent = (x0 - pitch / 2, x0 + (ix.max() + 0.5) * pitch, y0 - dy / 2, y0 + (iy.max() + 0.5) * dy)
    return img, extent


def sorter_lanes(setup, colours=("tab:blue", "tab:orange", "tab:green", "tab:purple")):
    """The entries and exits of a run whose program has them (program ``"sort"``: its module's ``markers``), as
    (label, colour, outline (k, 2) m): entries are grey, exit k takes ``colours[k]``, as the parcels bound for it.
    Empty for other runs."""
    if setup.scenario.control is None or setup.control is None:
        return []
    lanes = program_of(setup.scenario.control).markers(setup).lanes
    return [(label, "0.35" if k < 0 else colours[k % len(colours)], poly) for label, k, poly in lanes]


def draw_cells(ax, setup, size: float = 12, color: str = "0.45", label: str | None = "cells",
               cell_ids: bool = False, t: float | None = None) -> bool:
    """Draw the cells of ``setup`` into ``ax``: a dot per cell (``size`` points^2, ``color``, legend ``label``), each
    plain conveyor belt as a hatched outline, dead cells (:func:`dead_cells` at ``t``, None: at any time) as a dark
    X and cells out of the array (:func:`absent_cells`) as a dark hollow square. An array of more than
    :data:`LARGE_ARRAY` cells is drawn as one image instead (light grey cells, dead ones black, absent ones dark
    grey). ``cell_ids``: write each cell's id (its index in the layout's numbering) beside it (at most
    :data:`MAX_CELL_IDS` cells; ValueError beyond). Returns True when the array was drawn as an image."""
    cells = setup.cells
    P = cells.positions
    belt = cells.belts
    dead, absent = dead_cells(setup, t), absent_cells(setup, t)
    large = cells.n > LARGE_ARRAY
    if cell_ids and cells.n > MAX_CELL_IDS:
        raise ValueError(f"cell ids are drawn for at most {MAX_CELL_IDS} cells; this array has {cells.n}")
    if large:
        from matplotlib.colors import ListedColormap

        code = np.where(dead, 2.0, np.where(absent, 1.0, 0.0))
        img, extent = cell_raster(cells, code)
        ax.imshow(img, origin="lower", extent=extent, cmap=ListedColormap(["0.85", "0.45", "0.0"]), vmin=-0.5,
                  vmax=2.5, interpolation="nearest", zorder=0)
        ax.plot([], [], "s", color="0.85", label=f"{cells.n} cells (one pixel each)")
    else:
        ax.scatter(P[~belt, 0], P[~belt, 1], s=size, color=color, zorder=1, label=label)
    outlines = cell_outlines(cells, setup.contact_layer) if belt.any() else []
    for k, i in enumerate(np.flatnonzero(belt)):
        ax.add_patch(PolygonPatch(outlines[i], closed=True, facecolor="0.9", edgecolor="0.5", hatch="//", lw=0.8,
                                  zorder=0, label=None if k else "belt"))
    when = "" if t is not None else " (at some time)" if (setup.fault_events or setup.cell_changes) else ""
    free = dead.any() and setup.faults is not None and setup.faults.free_wheels[dead].all()
    dead_label = f"dead cell{when}" + (", wheels free" if free else "")  # ([faults] dead_wheels = "free")
    if dead.any():
        if large:
            ax.plot([], [], "s", color="0.0", label=dead_label)
        else:
            ax.scatter(P[dead, 0], P[dead, 1], s=max(4 * size, 40), marker="x", color="0.1", linewidths=2, zorder=4,
                       label=dead_label)
    if absent.any():
        if large:
            ax.plot([], [], "s", color="0.45", label=f"cell taken out{when}")
        else:
            ax.scatter(P[absent, 0], P[absent, 1], s=max(4 * size, 40), marker="s", facecolors="none",
                       edgecolors="0.1", linewidths=1.5, zorder=4, label=f"cell taken out{when}")
    if cell_ids:
        fs = float(np.clip(9 - 1.2 * np.log10(max(cells.n, 1)), 4.5, 8))
        for i in range(cells.n):
            ax.annotate(str(i), P[i], xytext=(2, 2), textcoords="offset points", fontsize=fs, color="0.2",
                        zorder=6, gid="cell-id")
    return large


def plot_sorting(result: RunResult, path: str | Path | None = None, cell_ids: bool = False):
    """A sorting run (program ``"sort"``): left, the array with its entry (grey) and exit lanes (one colour each),
    every parcel's path coloured by its destination, a filled dot where it left the array (at the right exit) or a
    red cross (elsewhere), and hollow squares for parcels still on it, the cells under parcels that stood still past
    the scenario's ``wait_bound`` (red squares where they wait on each other), dead cells crossed out (``cell_ids``:
    each cell's id written beside it); right, parcels delivered to the right exit and parcels on the array against
    time (s). Saves a PNG to ``path`` if given; returns the figure."""
    from virtual_vehicle.run.tasks import sorting_report

    setup = result.setup
    cells = setup.cells
    P = cells.positions
    cfg = setup.control.config
    report = sorting_report(result)
    fig, (ax, axt) = plt.subplots(1, 2, figsize=(13, 5.0), dpi=110, gridspec_kw={"width_ratios": [1.5, 1]})
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:purple"]
    draw_cells(ax, setup, size=8, color="0.75", label=None, cell_ids=cell_ids)
    ax.scatter(P[cfg["entry"], 0], P[cfg["entry"], 1], s=60, marker="s", color="0.55", zorder=1, label="entry")
    exits = np.asarray(cfg["exit"])
    for k in range(exits.max() + 1):
        sel = exits == k
        ax.scatter(P[sel, 0], P[sel, 1], s=60, marker="s", color=colors[k % 4], alpha=0.35, zorder=1,
                   label=f"exit {k}")
    for pr, row in zip(result.parcels, report["parcels"]):
        tr = pr.trajectory
        c = colors[(row["destination"] or 0) % 4]
        if row["outcome"] == "waiting":
            continue
        ax.plot(tr.states[:, 0], tr.states[:, 1], "-", color=c, lw=1.0, alpha=0.7, zorder=2)
        x, y = tr.states[-1, :2]
        if row["outcome"] == "delivered" and row["correct"]:
            ax.plot(x, y, "o", color=c, ms=6, zorder=3)
        elif row["outcome"] in ("delivered", "lost"):
            ax.plot(x, y, "x", color="red", ms=9, mew=2, zorder=3)
        else:
            end = pr.spec.world_polygon(tr.states[-1])
            ax.add_patch(PolygonPatch(np.asarray(end.exterior.coords), closed=True, fill=False, ec=c, lw=1.2))
    for k, stall in enumerate(report.get("stalls") or []):  # parcels that stood still past the bound
        where = P[stall["cells"]] if stall["cells"] else np.zeros((0, 2))
        if len(where):
            deadlock = stall["kind"] == "deadlock"
            ax.scatter(where[:, 0], where[:, 1], s=90, marker="s", facecolors="none", zorder=4,
                       edgecolors="red" if deadlock else "darkorange", lw=1.5,
                       label=None if k else "stalled (red: deadlocked) from the time shown")
            ax.annotate(f"{', '.join(stall['parcels'])} {stall['t_s']:.1f} s", where.mean(axis=0), fontsize=7,
                        color="red" if deadlock else "darkorange", ha="center", va="bottom", zorder=5)
    ax.set_aspect("equal")
    ax.margins(0.05)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    sc = setup.scenario
    ax.set_title(f"{sc.name}: paths coloured by destination")
    legend_below(ax, ncol=5)
    t = np.linspace(0.0, sc.duration, 400)
    done = [r["entered_at_s"] + r["delivery_time_s"] for r in report["parcels"] if r["correct"]]
    entered = [r["entered_at_s"] for r in report["parcels"] if r["entered_at_s"] is not None]
    left = [pr.trajectory.t_end for pr, r in zip(result.parcels, report["parcels"])
            if r["outcome"] in ("delivered", "lost")]
    axt.step(t, [sum(d <= ti for d in done) for ti in t], where="post", label="delivered to the right exit")
    on = [sum(e <= ti for e in entered) - sum(x <= ti for x in left) for ti in t]
    axt.step(t, on, where="post", label="on the array")
    axt.set_xlabel("t (s)")
    axt.set_ylabel("parcels")
    axt.set_title(f"{report['throughput_per_hour']:.0f} parcels/hour, {report['collisions']} collisions")
    axt.grid(alpha=0.3)
    axt.legend(loc="upper left", fontsize=8)
    return _finish(fig, path)


def plot_layout(setup, path: str | Path | None = None, cell_ids: bool = True, title: str | None = None):
    """The array of ``setup`` (a built scenario, not run) with each cell's id (its index in the layout's numbering:
    row by row from the bottom row up, left to right, see docs/layouts.md), the outline of each cell, the
    sorter's entries and exits (program ``"sort"``), dead cells crossed out, cells taken out hollow, and the
    parcels where they start. Saves a PNG to ``path`` if given; returns the figure."""
    from matplotlib.collections import PolyCollection

    cells = setup.cells
    xmin, ymin, xmax, ymax = cells.bounds
    aspect = (ymax - ymin + 2 * cells.pitch) / (xmax - xmin + 2 * cells.pitch)
    fig, ax = plt.subplots(figsize=(9.0, float(np.clip(9.0 * aspect, 3.0, 12.0)) + 1.2), dpi=110)
    if cells.n <= LARGE_ARRAY:
        ax.add_collection(PolyCollection(cell_outlines(cells, setup.contact_layer, 0.94), facecolors="0.96",
                                         edgecolors="0.7", linewidths=0.5, zorder=0))
    draw_cells(ax, setup, size=6, color="0.6", label="cell centre", cell_ids=cell_ids)
    for label, colour, poly in sorter_lanes(setup):
        ax.add_patch(PolygonPatch(poly, closed=True, fill=False, ec=colour, lw=2, zorder=2, label=label))
    for spec, state in zip(setup.specs, setup.states):
        ax.add_patch(PolygonPatch(np.asarray(spec.world_polygon(state).exterior.coords), closed=True, fill=False,
                                  ls="--", ec="tab:red", lw=1, zorder=3))
    ax.plot([], [], "--", color="tab:red", lw=1, label="parcels at the start")
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.04)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    sc = setup.scenario
    ax.set_title(title or f"{sc.name}: {cells.n} cells" + (", numbered row by row from the bottom" if cell_ids
                                                           else ""))
    legend_below(ax, ncol=4)
    return _finish(fig, path)


def plot_traffic(result: RunResult, path: str | Path | None = None):
    """Message traffic of a networked run: left, sentences each cell received over the run (colour) on the array,
    dead cells crossed out (an image for arrays of more than :data:`LARGE_ARRAY` cells); right, sentences sent and
    received per control tick, and below them the mean latency (ms) per tick on an axis from 0, or, when every
    sentence took the same time (ideal rounds: the next tick, by construction), that latency written in the title
    instead of a flat line. Saves a PNG to ``path``."""
    rec = result.network
    if rec is None:
        raise ValueError("this run has no network")
    setup = result.setup
    P = setup.cells.positions
    t = rec.per_tick["t"]
    lat = np.asarray(rec.per_tick["latency_mean"], dtype=float) * 1e3
    seen = lat[np.isfinite(lat) & (np.asarray(rec.per_tick["received"]) > 0)]
    constant = len(seen) == 0 or float(seen.max() - seen.min()) <= 1e-9 * max(1.0, float(np.abs(seen).max()))
    fig = plt.figure(figsize=(12.5, 5.0), dpi=110)
    grid = fig.add_gridspec(1 if constant else 2, 2, width_ratios=[1, 1.2], height_ratios=None if constant else [2, 1])
    ax = fig.add_subplot(grid[:, 0])
    axt = fig.add_subplot(grid[0, 1])
    recv = np.asarray(rec.per_cell["cell_received"], dtype=float)
    if setup.cells.n > LARGE_ARRAY:
        img, extent = cell_raster(setup.cells, recv)
        sc = ax.imshow(img, origin="lower", extent=extent, cmap="viridis", interpolation="nearest")
    else:
        sc = ax.scatter(P[:, 0], P[:, 1], c=recv, s=260, marker="s", cmap="viridis", edgecolors="0.3")
    fig.colorbar(sc, ax=ax, label="sentences received per cell")
    dead = dead_cells(setup)
    if dead.any():
        ax.scatter(P[dead, 0], P[dead, 1], s=90, marker="x", color="white", linewidths=2.5, zorder=3)
        ax.scatter(P[dead, 0], P[dead, 1], s=60, marker="x", color="crimson", linewidths=1.5, zorder=4,
                   label="dead cell")
        legend_below(ax)
    ax.set_aspect("equal")
    ax.margins(0.15)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"traffic per cell ({rec.delivery} delivery)")
    axt.step(t, rec.per_tick["sent"], where="post", lw=1.8, color="tab:blue", alpha=0.6, label="sent")
    axt.step(t, rec.per_tick["received"], where="post", lw=1.0, color="tab:orange", ls="--", label="received")
    axt.set_ylabel("sentences per tick")
    axt.set_ylim(bottom=0)
    axt.legend(loc="upper right", fontsize=8)
    axt.grid(alpha=0.3)
    title = f"sentences per {rec.period * 1e3:g} ms tick"
    if constant:
        if len(seen):  # a flat latency line says nothing: write it down
            note = f"every sentence took {seen[0]:.3g} ms"
            if rec.delivery == "ideal":
                note += "\n(ideal rounds: the next tick, by construction)"
            axt.text(0.02, 0.97, note, transform=axt.transAxes, va="top", fontsize=8,
                     bbox=dict(boxstyle="round,pad=0.3", fc="white", ec="0.7", alpha=0.9), gid="latency-note")
        axt.set_xlabel("t (s)")
    else:
        axl = fig.add_subplot(grid[1, 1], sharex=axt)
        axl.plot(t, lat, ".", ms=3, color="tab:red")
        axl.set_ylim(0.0, 1.1 * float(np.nanmax(seen)))
        axl.set_ylabel("mean latency (ms)")
        axl.set_xlabel("t (s)")
        axl.grid(alpha=0.3)
        plt.setp(axt.get_xticklabels(), visible=False)
    axt.set_title(title)
    return _finish(fig, path)


def plot_force_field(cells, spec, velocities, law, heading: float, eqs=(), path: str | Path | None = None,
                     bounds=None, step: float | None = None, gravity: float = 9.81, title: str | None = None):
    """The force (arrows, N) and torque (colour, N m) a field induces on ``spec`` at rest with heading ``heading``
    (rad), over centre-of-mass positions (m) in ``bounds`` = (xmin, ymin, xmax, ymax), with the equilibria ``eqs``
    (:func:`~virtual_vehicle.analysis.equilibria.equilibria`) marked: filled = stable or marginal, hollow = neutral, x =
    unstable; labelled with their headings in degrees when there are at most 12. Saves a PNG to ``path`` if given;
    returns the figure."""
    from virtual_vehicle.engine.dynamics import ParcelModel
    from virtual_vehicle.errors import TippingError

    model = ParcelModel(cells, spec, np.asarray(velocities, dtype=float), law, gravity)
    xmin, ymin, xmax, ymax = cells.bounds if bounds is None else bounds
    step = step or cells.pitch / 4
    xs = np.arange(xmin, xmax + 0.5 * step, step)
    ys = np.arange(ymin, ymax + 0.5 * step, step)
    F = np.full((len(ys), len(xs), 2), np.nan)
    T = np.full((len(ys), len(xs)), np.nan)
    for b, y in enumerate(ys):
        for a, x in enumerate(xs):
            try:
                d = model.rhs(0.0, np.array([x, y, heading, 0.0, 0.0, 0.0]))
            except TippingError:
                continue
            F[b, a] = d[3:5] * spec.mass
            T[b, a] = d[5] * spec.inertia
    fig, ax = plt.subplots(figsize=(7.2, 6.0), dpi=110)
    mag = np.hypot(F[..., 0], F[..., 1])
    top = float(np.nanmax(mag)) if np.any(np.isfinite(mag)) else 0.0
    lim = float(np.nanmax(np.abs(T))) if np.any(np.isfinite(T)) else 0.0
    # a torque under a thousandth of the largest force at the footprint's reach is drawn as none: rounding (~1e-17 N m
    # where the field is symmetric) would otherwise fill the whole colour scale
    lim = max(lim, 1e-3 * top * float(np.max(np.hypot(*spec.footprint.T)))) or 1.0
    mesh = ax.pcolormesh(xs, ys, T, cmap="coolwarm", vmin=-lim, vmax=lim, shading="nearest", alpha=0.85)
    fig.colorbar(mesh, ax=ax, shrink=0.8, label="torque (N m, counter-clockwise +)")
    X, Y = np.meshgrid(xs, ys)
    if top > 0:  # at most ~24 arrows a side, so they stay readable
        every = max(1, int(np.ceil(max(len(xs), len(ys)) / 24)))
        k = 0.85 * every * step / top
        sl = (slice(None, None, every), slice(None, None, every))
        ax.quiver(X[sl], Y[sl], F[sl][..., 0] * k, F[sl][..., 1] * k, angles="xy", scale_units="xy", scale=1,
                  width=0.0035, color="0.1", alpha=0.8, label=f"force at rest (longest {top:.3g} N)")
    P = cells.positions
    ax.scatter(P[:, 0], P[:, 1], s=14, marker="s", color="0.35", zorder=3, label="cells")
    style = {"stable": dict(marker="o", color="tab:green", ms=8),
             "neutral": dict(marker="o", mfc="none", color="tab:green", ms=8, mew=2),
             "unstable": dict(marker="x", color="tab:red", ms=8, mew=2)}
    names = {"stable": "stable equilibrium", "neutral": "neutral in heading", "unstable": "unstable equilibrium"}
    shown = set()
    for e in eqs:
        x, y, th = e.pose
        kind = "unstable" if not e.stable else ("neutral" if e.rotation == "neutral" else "stable")
        ax.plot(x, y, ls="none", zorder=4, label=None if kind in shown else names[kind], **style[kind])
        shown.add(kind)
        if len(eqs) <= 12:
            label = (f"{np.degrees(e.heading_range[0]):.0f}..{np.degrees(e.heading_range[1]):.0f}°"
                     if e.heading_range else f"{np.degrees(th):.1f}°")
            ax.annotate(label, (x, y), xytext=(6, 6), textcoords="offset points", fontsize=7)
    outline = spec.world_polygon((0.5 * (xmin + xmax), 0.5 * (ymin + ymax), heading))
    ax.add_patch(PolygonPatch(np.asarray(outline.exterior.coords), closed=True, fill=False, ls="--", ec="0.2",
                              lw=1, label="parcel at the centre"))
    ax.set_aspect("equal")
    ax.set_xlabel("centre of mass x (m)")
    ax.set_ylabel("centre of mass y (m)")
    ax.set_title(title or f"force and torque on {spec.name} at heading {np.degrees(heading):.1f}°")
    legend_below(ax, ncol=3)
    return _finish(fig, path)


def plot_similarity(rows: list[dict], title: str, path: str | Path | None = None):
    """Overlay the first parcel's dimensionless path of every member of a similarity family (rows of
    :func:`~virtual_vehicle.analysis.scaling.similarity_study`): x / L and y / L against t / sqrt(L / g), one line style
    per scale, labelled with its pitch (m) and parcel mass (kg). Similar runs draw one curve. Saves a PNG to ``path`` if
    given; returns the figure."""
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=110)
    styles = ["-", "--", ":", "-."]
    for k, r in enumerate(rows):
        label = f"pitch {r['pitch_m']:.3g} m, mass {r['mass_kg']:.3g} kg"
        ax.plot(r["tau"], r["states"][:, 0], styles[k % 4], color="tab:blue", lw=2.5 - 0.5 * (k % 4),
                label=f"x/L, {label}")
        ax.plot(r["tau"], r["states"][:, 1], styles[k % 4], color="tab:orange", lw=2.5 - 0.5 * (k % 4),
                label=f"y/L, {label}")
    ax.set_xlabel("t / sqrt(L / g)")
    ax.set_ylabel("position / L")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _finish(fig, path)


def fault_study_outcomes(rows: list[dict]) -> dict[str, np.ndarray]:
    """Mean parcels per run of each outcome, per row of a fault study
    (:func:`~virtual_vehicle.analysis.sweep.fault_study`): ``delivered`` (to the right exit), ``misrouted``, ``lost``
    and ``not_delivered`` (still on the array or never put on at the end of the run: parcels due minus delivered,
    misrouted and lost), which sum to ``parcels_due``. When the rows carry ``on_array`` and ``waiting`` (mean parcels
    per run), ``not_delivered`` is split into those two, and when they carry ``deadlocked`` too, ``on_array`` into
    ``deadlocked`` (in a cycle of holds the run's report names) and ``on_array`` (the rest: moving, or waiting on
    the floor or behind others). NaN where a rate has no finished run."""
    def col(key):
        return np.array([np.nan if r.get(key) is None else r[key] for r in rows], dtype=float)

    due = col("parcels_due")
    out = {"delivered": col("delivered_fraction") * due, "misrouted": col("misrouted"), "lost": col("lost")}
    if all(r.get("on_array") is not None and r.get("waiting") is not None for r in rows):
        out["on_array"], out["waiting"] = col("on_array"), col("waiting")
        if all(r.get("deadlocked") is not None for r in rows):
            out["deadlocked"] = col("deadlocked")
            out["on_array"] = out["on_array"] - out["deadlocked"]
            out = {k: out[k] for k in ("delivered", "misrouted", "lost", "deadlocked", "on_array", "waiting")}
    else:
        out["not_delivered"] = np.clip(due - out["delivered"] - out["misrouted"] - out["lost"], 0.0, None)
    return out


_OUTCOME_STYLE = {"delivered": ("delivered to the right exit", "tab:green"),
                  "misrouted": ("misrouted (wrong exit)", "tab:orange"), "lost": ("lost (left elsewhere)", "tab:red"),
                  "not_delivered": ("stuck: still on the array or never put on", "0.45"),
                  "on_array": ("waiting on the array at the end", "0.45"), "waiting": ("never put on (entry blocked)",
                                                                              "0.75"),
                  "deadlocked": ("deadlocked (a cycle of holds)", "tab:purple")}


def plot_fault_study(rows: list[dict], kind: str, title: str, path: str | Path | None = None):
    """A fault study (:func:`~virtual_vehicle.analysis.sweep.fault_study`): left, the fraction of parcels delivered to
    the right exit against the failure rate, each fault draw a dot (rows with ``draws``; else one standard deviation
    about the mean, cut at 0 and 1) and the mean over the draws joined by a line; middle, what became
    of the parcels due (mean per run, stacked: delivered, misrouted, lost, and those stuck on the array or never put on,
    :func:`fault_study_outcomes`) with the collisions per run; right, the mean delivery time (s) on an axis from 0, its
    spread over the rates written out. Saves a PNG to ``path`` if given."""
    rate = np.array([r["rate"] for r in rows])

    def col(key):
        return np.array([np.nan if r.get(key) is None else r[key] for r in rows], dtype=float)

    fig, (ax, axo, axt) = plt.subplots(1, 3, figsize=(15.5, 4.6), dpi=110, gridspec_kw={"width_ratios": [1, 1.2, 1]})
    xlabel = f"{kind.replace('_', ' ')} (probability per item)"
    frac, std = col("delivered_fraction"), col("delivered_fraction_std")
    span = float(np.ptp(rate)) if len(rate) > 1 else 0.0
    # one rate: an axis about it (matplotlib's default is +-0.05 around a point, or +-0.4 % of it)
    half = 0.5 * max(abs(float(rate[0])), 0.01)
    one = None if span > 0 else (float(rate[0]) - half, float(rate[0]) + half)
    if all(r.get("draws") for r in rows):  # each draw: where a rate's draws split, the mean is no draw's figure
        jitter = 0.012 * (span if one is None else one[1] - one[0])
        for j, (x, r) in enumerate(zip(rate, rows)):
            fr = np.asarray(r["draws"]["delivered_fraction"], dtype=float)
            ax.plot(x + np.linspace(-jitter, jitter, len(fr)) * (len(fr) > 1), fr, "o", ms=3.5, color="tab:blue",
                    alpha=0.45, mec="none", label="one fault draw" if j == 0 else None)
        ax.plot(rate, frac, "D-", ms=6, color="navy", label="mean over the draws")
        ax.legend(fontsize=8, loc="best", frameon=False)
    else:  # (rows from before the draws were kept) one standard deviation, within what a fraction can be
        ax.errorbar(rate, frac, yerr=[np.minimum(std, frac), np.minimum(std, 1.0 - frac)], marker="o", capsize=4,
                    color="tab:blue")
    ax.set_ylim(-0.02, 1.02)
    if one is not None:
        ax.set_xlim(*one)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("fraction delivered to the right exit")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    # what became of the parcels: stacked bars, one per rate, summing to the parcels due
    outcomes = fault_study_outcomes(rows)
    pos = np.arange(len(rows))
    bottom = np.zeros(len(rows))
    for key, vals in outcomes.items():
        label, colour = _OUTCOME_STYLE[key]
        v = np.nan_to_num(vals)
        axo.bar(pos, v, 0.6, bottom=bottom, color=colour, edgecolor="white", label=label, zorder=2)
        for x, b, h in zip(pos, bottom, v):
            if h >= 0.06 * max(1.0, np.nanmax(col("parcels_due"))):
                axo.text(x, b + h / 2, f"{h:.3g}", ha="center", va="center", fontsize=8,
                         color="white" if colour not in ("0.75",) else "black")
        bottom += v
    coll = col("collisions")
    axo.plot(pos, coll, "kD--", ms=5, lw=1, label="collisions per run (pairs)", zorder=3)
    none = [name for name, v in (("misrouted", outcomes["misrouted"]), ("lost", outcomes["lost"]),
                                 ("collisions", coll)) if np.all(np.nan_to_num(v) == 0)]
    if none:  # a zero bar is invisible: say so
        axo.text(0.5, 0.785, f"0 {', 0 '.join(none)} at every rate", transform=axo.transAxes, ha="center", fontsize=8,
                 color="0.2")
    axo.set_xticks(pos, [f"{r:g}" for r in rate])
    axo.set_xlabel(xlabel)
    axo.set_ylabel("parcels per run (mean)")
    top = max(1.0, float(np.nanmax(np.concatenate([bottom, np.nan_to_num(coll)]))))
    axo.set_ylim(0.0, 1.35 * top)  # room for the legend above the bars
    axo.set_title("what became of the parcels due")
    axo.legend(fontsize=7, loc="upper center", ncol=2, frameon=False)
    axo.grid(alpha=0.3, axis="y", zorder=0)
    times = col("delivery_time_mean_s")
    axt.plot(rate, times, "o-", color="tab:green", label="mean delivery time")
    axt.set_ylim(0.0, 1.2 * max(1e-9, float(np.nanmax(times))) if np.any(np.isfinite(times)) else 1.0)
    if np.any(np.isfinite(times)):
        lo, hi = float(np.nanmin(times)), float(np.nanmax(times))
        axt.text(0.03, 0.04, f"spread over the rates: {lo:.4g} .. {hi:.4g} s", transform=axt.transAxes, fontsize=8)
    if one is not None:
        axt.set_xlim(*one)
    axt.set_xlabel(xlabel)
    axt.set_ylabel("delivery time (s)")
    axt.grid(alpha=0.3)
    axt.set_title("mean delivery time of the delivered")
    return _finish(fig, path)


def legend_below(ax, handles=None, labels=None, ncol: int = 1, fontsize: float = 8):
    """A legend centred under ``ax``, below its tick labels and x label at any height of the axes: its gap is set in
    points (``borderaxespad`` counts font sizes), not as a fraction of the axes, which on a short axes (a row of
    cells drawn to scale) put it over the x label."""
    extra = () if handles is None else (handles, labels)
    return ax.legend(*extra, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=ncol, fontsize=fontsize,
                     frameon=False, borderaxespad=34.0 / fontsize)


def _finish(fig, path):
    """Lay out, save as PNG (atomically) when ``path`` is given, release the figure's memory, return it."""
    try:
        fig.tight_layout()
        if path is not None:
            buf = _io.BytesIO()
            fig.savefig(buf, format="png")
            write_atomic(Path(path), buf.getvalue())
    finally:
        plt.close(fig)
    return fig
