"""A finished run replayed from its run folder (``virtual-vehicle view RUN_FOLDER``): :class:`Replay` reads the
folder back (its scenario for the array's shape and faults, its tables for what happened) and says what was on the
array at any time; :func:`build` is its page, drawn as the live one, with a time scrubber (a slider and play).

What is drawn comes from what was recorded: the parcels' poses from ``trajectories`` (linear between samples, as
the animation does), their arrivals, ends and stalls from ``summary.json``, dead and removed cells from the
scenario's faults at that time, lit sensors and wheel speeds from the ``cells`` table when the run recorded it
(``[sensors] record = true``; else the sensors the parcels' footprints cover, and no wheel arrows), and the cells'
traffic from it (per tick) or from ``cell_traffic`` (the whole run's). Units: m, s.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from virtual_vehicle.config.scenario import parse_text
from virtual_vehicle.ui.view.draw import ABSENT, DEAD, EMPTY, EXIT_COLOURS, STALL, ArrayView, place_labels, ramp
from virtual_vehicle.ui.viz import absent_cells, dead_cells

NEEDED = ("scenario.toml", "summary.json", "trajectories")
"""What a folder must hold to be replayed (``trajectories`` as .parquet or .csv)."""


def _table(folder: Path, name: str):
    """The table ``name`` of the run folder as a pyarrow Table (Parquet preferred, else CSV), or None."""
    if (folder / f"{name}.parquet").is_file():
        import pyarrow.parquet as pq

        return pq.read_table(folder / f"{name}.parquet")
    if (folder / f"{name}.csv").is_file():
        import pyarrow.csv as pc

        return pc.read_csv(folder / f"{name}.csv")
    return None


@dataclass(frozen=True)
class ReplayFrame:
    """What the replay shows at time ``t`` (s): ``poses`` name -> (x, y, theta) of the parcels on the array (m, rad);
    ``waiting`` the parcels due but not let on yet; ``stalled`` name -> ``"deadlock"`` or ``"waiting"`` for the
    parcels of a stall (``sorting.stalls``) going on at t; ``dead``, ``absent`` (n,) bool cells; ``lit`` (n, S)
    bool sensors; ``lit_recorded`` whether ``lit`` is as read (else the footprints' cover); ``wheels`` (n, 2) m/s
    each wheel's surface speed over the tick, or None when not recorded; ``traffic`` (n,) sentences received per s
    (over the tick when recorded per tick, else over the whole run), or None without a network."""

    t: float
    poses: dict
    waiting: list
    stalled: dict
    dead: np.ndarray
    absent: np.ndarray
    lit: np.ndarray
    lit_recorded: bool
    wheels: np.ndarray | None
    traffic: np.ndarray | None


class Replay:
    """A run folder read back, with a time ``t`` (s) that the page's scrubber and play move.

    Args:
        folder: a folder written by ``virtual-vehicle run`` (or ``view``).

    Raises ValueError for a folder that is not a run folder (saying what it lacks), ScenarioError when its
    scenario.toml does not load.
    """

    def __init__(self, folder: str | Path):
        folder = Path(folder)
        if not folder.is_dir():
            raise ValueError(f"{folder} is not a run folder: no such folder")
        lacking = [n for n in NEEDED if not ((folder / n).is_file() or (folder / f"{n}.parquet").is_file()
                                             or (folder / f"{n}.csv").is_file())]
        if lacking:
            raise ValueError(f"{folder} is not a run folder (as 'virtual-vehicle run' writes): it has no "
                             f"{', '.join(lacking)}")
        self.folder = folder
        self.scenario = parse_text((folder / "scenario.toml").read_text(), str(folder / "scenario.toml"))
        self.setup = self.scenario.build()
        self.summary = json.loads((folder / "summary.json").read_text())
        self.duration = float(self.scenario.duration)
        ctl = self.scenario.control
        self.period = float(ctl.period) if ctl is not None else float(self.scenario.output_dt or self.duration / 500)
        self._tree = cKDTree(self.setup.cells.positions)
        self.names = [s.name for s in self.setup.specs]
        rows = {r["name"]: r for r in self.summary.get("parcels", [])}
        self.rows = [rows.get(n, {}) for n in self.names]
        traj = _table(folder, "trajectories").to_pydict()
        order = np.lexsort((np.asarray(traj["t"]), np.asarray([self.names.index(p) for p in traj["parcel"]])))
        names = np.asarray(traj["parcel"])[order]
        states = np.column_stack([np.asarray(traj[k], float)[order] for k in ("t", "x", "y", "theta")])
        self.paths = {n: states[names == n] for n in self.names}
        # when each parcel came on: a networked run reports it (None: never let on); a field run's parcels are on
        # from their first sample
        self.entered = [row["entered_at_s"] if "entered_at_s" in row else
                        float(self.paths[n][0, 0]) if len(self.paths[n]) else None
                        for n, row in zip(self.names, self.rows)]
        self.stalls = (self.summary.get("sorting") or {}).get("stalls") or []
        self._cells_log(folder)
        self.t = 0.0

    def _cells_log(self, folder: Path) -> None:
        """The per-tick cell log (``cells`` table) as arrays, when the run recorded it; the run's traffic else."""
        n = self.setup.cells.n
        self.log_t = self.log_lit = self.log_wheels = self.log_received = None
        cells = _table(folder, "cells")
        if cells is not None:
            d = cells.to_pydict()
            t = np.asarray(d["t"], float)
            order = np.lexsort((np.asarray(d["cell"]), t))
            self.log_t = t[order][::n]
            S = sum(1 for k in d if k.startswith("s") and k[1:].isdigit())
            self.log_lit = np.column_stack([np.asarray(d[f"s{j}"], bool)[order] for j in range(S)]).reshape(-1, n, S)
            self.log_wheels = np.column_stack([np.asarray(d[f"wheel{j}"], float)[order] for j in (0, 1)]) \
                .reshape(-1, n, 2)
            self.log_received = np.asarray(d["received"], float)[order].reshape(-1, n)
        traffic = _table(folder, "cell_traffic")
        self.run_traffic = None
        if traffic is not None:
            d = traffic.to_pydict()
            self.run_traffic = np.zeros(n)
            self.run_traffic[np.asarray(d["cell"], int)] = np.asarray(d["received"], float) / self.duration

    # the time the page moves
    @property
    def done(self) -> bool:
        """True once the replay has reached the run's end."""
        return self.t >= self.duration

    def seek(self, t: float) -> None:
        """Go to time ``t`` s (clipped to the run: 0 .. duration)."""
        self.t = float(np.clip(t, 0.0, self.duration))

    def advance(self, sim_seconds: float, budget: float = math.inf) -> None:
        """Move ``sim_seconds`` s on (``budget``, real time, is not needed: nothing is computed)."""
        self.seek(self.duration if not math.isfinite(sim_seconds) else self.t + sim_seconds)

    def tick(self) -> None:
        """Move one control period (the output step without control) on."""
        self.seek(self.t + self.period)

    # what was there
    def frame(self, t: float | None = None) -> ReplayFrame:
        """What the run showed at ``t`` s (default: the replay's time); see :class:`ReplayFrame`."""
        t = self.t if t is None else float(t)
        poses, waiting = {}, []
        for name, row, entered in zip(self.names, self.rows, self.entered):
            due = row.get("due_s")
            path = self.paths[name]
            if entered is not None and entered <= t + 1e-12 and t <= row.get("t_end_s", self.duration) + 1e-12 \
                    and len(path) and path[0, 0] <= t + 1e-12:
                poses[name] = tuple(float(np.interp(t, path[:, 0], path[:, j])) for j in (1, 2, 3))
            elif due is not None and due <= t + 1e-12 and (entered is None or t < entered):
                waiting.append(name)
        stalled = {}
        for stall in self.stalls:
            if stall["t_s"] <= t + 1e-12 and t <= stall["t_s"] + stall["waited_s"] + 1e-12:
                for name in stall["parcels"]:
                    stalled[name] = stall["kind"]
        wheels = traffic = None
        n = self.setup.cells.n
        if self.log_t is not None and len(self.log_t):
            k = int(np.clip(np.searchsorted(self.log_t, t + 1e-12, side="right") - 1, 0, len(self.log_t) - 1))
            lit, recorded, wheels = self.log_lit[k], True, self.log_wheels[k]
            traffic = self.log_received[k] / self.period
        else:
            on = [name in poses for name in self.names]
            states = [np.array([*poses.get(name, (0.0, 0.0, 0.0)), 0.0, 0.0, 0.0]) for name in self.names]
            lit, recorded = self.setup.sensors.covered(self.setup.specs, states, active=on), False
            traffic = self.run_traffic
        return ReplayFrame(t, poses, waiting, stalled, dead_cells(self.setup, t), absent_cells(self.setup, t),
                           lit, recorded, wheels, traffic if traffic is None else np.asarray(traffic, float)[:n])

    def cell_colours(self, frame: ReplayFrame) -> tuple[np.ndarray, str]:
        """(n, 3) colours of the cells at ``frame`` (traffic, white to orange) and the legend's words for them."""
        n = self.setup.cells.n
        if frame.traffic is None:
            rgb, note = np.tile(np.asarray(EMPTY, float), (n, 1)), "no network: cells plain"
        else:
            working = frame.traffic[~(frame.dead | frame.absent)]
            low, top = np.percentile(working, (50, 99)) if len(working) else (0.0, 0.0)
            span = "this tick" if self.log_t is not None else "the whole run"
            if top > low:
                rgb = ramp((frame.traffic - low) / (top - low), EMPTY, (230, 120, 20))
                note = f"traffic over {span}: white {low:.3g} (the median) .. orange {top:.3g} sentences per s"
            else:
                rgb = np.tile(np.asarray(EMPTY, float), (n, 1))
                note = f"traffic over {span}: no cell above the median, {low:.3g} sentences per s"
        rgb[frame.absent] = ABSENT
        rgb[frame.dead] = DEAD
        return rgb, note + "; dead cells black, cells taken out grey"

    def parcel_data(self, frame: ReplayFrame) -> tuple[dict, dict]:
        """The parcels on the array and those waiting at ``frame``, as columns for the page's sources (as the live
        page's: stalled parcels outlined thick in red, named with the stall's kind)."""
        specs = dict(zip(self.names, self.setup.specs))
        dests = {p.name: p.destination for p in self.scenario.parcels}
        on = {"xs": [], "ys": [], "fill": [], "line": [], "width": [], "x": [], "y": [], "label": []}
        for name, pose in frame.poses.items():
            ring = np.asarray(specs[name].world_polygon(pose).exterior.coords)
            d = dests.get(name)
            colour = "#777777" if d is None else EXIT_COLOURS[d % len(EXIT_COLOURS)]
            label = name if d is None else f"{name}→{d}"
            kind = frame.stalled.get(name)
            for key, value in (("xs", ring[:, 0]), ("ys", ring[:, 1]), ("fill", colour),
                               ("line", STALL if kind else colour), ("width", 3.5 if kind else 1.5),
                               ("x", pose[0]), ("y", pose[1]), ("label", f"{label} {kind}" if kind else label)):
                on[key].append(value)
        wait = {"xs": [], "ys": [], "x": [], "y": [], "label": []}
        places: dict[tuple, list] = {}
        for name in frame.waiting:
            spec = specs[name]
            p = next(q for q in self.scenario.parcels if q.name == name)
            ring = np.asarray(spec.world_polygon((p.x, p.y, p.theta)).exterior.coords)
            places.setdefault((round(p.x, 6), round(float(ring[:, 1].min()), 6)), []).append((name, ring))
        place_labels(wait, places)
        return on, wait

    def counts(self, times: np.ndarray) -> dict[str, np.ndarray]:
        """Parcels on the array, waiting and gone (left the array) at each of ``times`` (s), for the charts."""
        on, waiting, left = (np.zeros(len(times)) for _ in range(3))
        for row, entered in zip(self.rows, self.entered):
            due, end = row.get("due_s"), row.get("t_end_s", self.duration)
            if entered is not None:
                on += (times >= entered) & (times <= end)
                if row.get("outcome") in ("delivered", "lost"):
                    left += times > end
            if due is not None:
                waiting += (times >= due) & ((times < entered) if entered is not None else True)
        return {"on": on, "waiting": waiting, "left": left}


def build(doc, viewer):
    """Lay out the replay page of one browser session on ``doc`` (the array as the live page draws it, a time
    slider, play and speed, the parcels' counts and the network's traffic against time) and return its refresh."""
    from bokeh.layouts import column, row
    from bokeh.models import Button, ColumnDataSource, Div, NumeralTickFormatter, Slider, Span
    from bokeh.plotting import figure

    replay: Replay = viewer.live
    view = ArrayView(replay.setup, replay._tree, f"replay of {replay.folder}")
    step = replay.period if replay.duration / replay.period <= 20_000 else replay.duration / 20_000
    scrub = Slider(name="time", title="simulated time (s)", start=0.0, end=replay.duration, step=step,
                   value=replay.t, width=900)
    play = Button(name="play", label="play" if not viewer.playing else "pause", button_type="primary", width=80)
    speed = Slider(name="speed", title="speed (log10 of simulated s per real s)", start=-1.0, end=2.0, step=0.1,
                   value=math.log10(viewer.speed), width=260)
    status = Div(name="status", styles={"font-family": "monospace", "font-size": "13px"})
    legend = Div(name="legend", width=900, styles={"font-size": "12px", "color": "#333"})
    times = np.linspace(0.0, replay.duration, 401)
    charts, spans = [], []
    counts = ColumnDataSource({"t": times, **replay.counts(times)})
    c = figure(title="parcels", width=420, height=240, x_axis_label="simulated time (s)", tools="")
    for key, colour in (("left", "#2ca02c"), ("on", "#1f77b4"), ("waiting", "#d62728")):
        c.line("t", key, source=counts, color=colour, line_width=2, legend_label=key)
    c.legend.orientation = "horizontal"
    c.add_layout(c.legend[0], "above")
    charts.append(c)
    network = _table(replay.folder, "network")
    if network is not None:
        d = network.to_pydict()
        net = ColumnDataSource({"t": d["t"], "rate": np.asarray(d["received"], float) / replay.period})
        c = figure(title="sentences received per simulated s", width=420, height=190,
                   x_axis_label="simulated time (s)", tools="")
        c.yaxis.formatter = NumeralTickFormatter(format="0.[00]a")
        c.line("t", "rate", source=net, color="#e6781e", line_width=1.5)
        charts.append(c)
    for c in charts:
        c.y_range.start = 0
        spans.append(Span(location=replay.t, dimension="height", line_color="#444444", line_dash="dashed"))
        c.add_layout(spans[-1])
    moving = {"by_page": False}

    def on_scrub(attr, old, new) -> None:
        if not moving["by_page"]:
            replay.seek(new)

    def on_play() -> None:
        if replay.done:
            replay.seek(0.0)
        viewer.playing = not viewer.playing

    def on_speed(attr, old, new) -> None:
        viewer.speed = 10 ** new

    scrub.on_change("value", on_scrub)
    play.on_click(on_play)
    speed.on_change("value_throttled", on_speed)

    def refresh() -> None:
        frame = replay.frame()
        rgb, note = replay.cell_colours(frame)
        on, wait = replay.parcel_data(frame)
        lit = replay.setup.sensors.points[frame.lit] if frame.lit.any() else np.zeros((0, 2))
        view.show(rgb, lit, frame.wheels, on, wait)
        if scrub.value != replay.t:
            moving["by_page"] = True
            scrub.value = replay.t
            moving["by_page"] = False
        for s in spans:
            if s.location != replay.t:
                s.location = replay.t
        if replay.done:
            viewer.playing = False
        play.label = "pause" if viewer.playing else "play"
        stalls = ", ".join(f"{k} {v}" for k, v in frame.stalled.items())
        status.text = (f"t = {replay.t:.2f} s of {replay.duration:g} s &nbsp; on the array {len(frame.poses)} "
                       f"&nbsp; waiting {len(frame.waiting)}" + (f" &nbsp; stalled: {stalls}" if stalls else "")
                       + f" &nbsp; {'playing' if viewer.playing else 'paused'}")
        names = "" if view.labels_on else "Parcels' names and destinations: hover over them. "
        legend.text = (f"{note}. {names}Red dots: sensors {'lit as read' if frame.lit_recorded else 'under a parcel'}"
                       f"{'' if frame.wheels is not None else ' (no cell log recorded: no wheel arrows)'}. Parcels "
                       "coloured by their exit; red thick outline: in a stall (deadlock: parcels waiting on each "
                       "other; waiting: alone); red dashed: due but waiting for its place.")

    refresh()
    doc.add_periodic_callback(refresh, int(1000 * viewer.frame))
    doc.add_root(column(row(play, speed), scrub, status, row(view.figure, column(*charts)), legend))
    doc.title = f"virtual-vehicle view: replay of {replay.scenario.name}"
    return refresh
