"""Watch and steer a networked run live in a browser (``virtual-vehicle view SCENARIO``).

:class:`LiveRun` is the run under the viewer: the same control tick as ``virtual-vehicle run``
(:class:`~virtual_vehicle.run.sim.NetworkRun`), stepped from outside, and a record of what the viewer did to it.
A cell killed or revived is a ``[[faults.events]]`` table at the time of the next tick (a cell killed at t = 0 is
one of ``[faults] dead_cells``); a parcel dropped at an entry is a ``[[parcels]]`` table with ``t_start`` = that time.
After each such change the run is made afresh from the changed scenario and ticked up to where it was, so the run
on screen *is* the run of the scenario it writes: ``virtual-vehicle run`` of that scenario gives the same tables,
bit for bit.

:func:`serve` puts it on a page with Bokeh's server. Why Bokeh: its wheel ships BokehJS (nothing is fetched from
the internet at run time), it streams ColumnDataSources and images over one websocket in binary, it runs on
Tornado, which Dask's distributed scheduler already brings, and its signed session ids are the access token
(Jupyter-style): a request without a valid one is refused with 403. The page binds 127.0.0.1 unless told otherwise.

The page: the cells as one image layer (coloured by traffic, the program's state or the hop distance to the
nearest exit; dead cells black, cells taken out dark grey), lit sensors, entries and exits, the parcels (outlines,
names, destinations; those due but not yet let on, and those standing still, outlined in red), and live charts of
the real-time factor, the sentences received per second and the parcels that left the array (delivered), are on it
and wait, against simulated time. Units: m, s.
"""

from __future__ import annotations

import math
import secrets
import socket
import time
from pathlib import Path

import numpy as np
import shapely
from scipy.spatial import cKDTree

from virtual_vehicle.config.scenario import FaultEvent, ParcelEntry, Scenario, dump_toml, load_scenario, parse_text
from virtual_vehicle.run.sim import NetworkRun, RunResult, carry_on
from virtual_vehicle.ui.viz import absent_cells, dead_cells, sorter_lanes

COLOUR_BY = ("traffic", "program state", "hop distance")
"""What the cells' colour can show: sentences received per tick, the program's first per-cell state word (for the
sorter: which parcel the cell carries) or the hop distance to the nearest exit (the sorter's gradients)."""
SPEEDS = (0.1, 10.0)
"""The range of simulated seconds per real second the page's speed slider sets (``math.inf``: as fast as it
runs)."""
LOOPBACK = ("127.0.0.1", "localhost", "::1")
"""Addresses that serve the page to this machine alone."""
STILL = 1e-3
"""m/s: a parcel on the array slower than this is outlined as standing still."""


class _ViewedRun(NetworkRun):
    """A networked run that keeps what the page draws: the last readings and the wheel speeds held."""

    def begin(self) -> np.ndarray:
        self.readings = super().begin()
        return self.readings

    def finish(self, command, sensors, sent, received) -> np.ndarray:
        self.wheels = super().finish(command, sensors, sent, received)
        return self.wheels


class LiveRun:
    """A networked run stepped from outside, and the record of what was done to it.

    Args:
        scenario: a bundled scenario's name, a TOML path or a :class:`Scenario` with a ``[control]`` table.

    Raises ScenarioError for a scenario that does not load or build, and ValueError for one without ``[control]``.
    """

    def __init__(self, scenario: str | Path | Scenario):
        if isinstance(scenario, Scenario):
            sc, text = scenario, None
        else:
            sc, text = load_scenario(scenario)
        if sc.control is None:
            raise ValueError("the viewer steps a networked run: the scenario needs a [control] table")
        self.text = text
        self.actions: list[dict] = []
        self.wall = 0.0  # s of real time spent ticking, replays left out
        self._make(sc, 0)

    def _make(self, sc: Scenario, k: int) -> None:
        """The run of ``sc`` made afresh and ticked ``k`` times (the ticks before a change are not changed by it)."""
        run = _ViewedRun(sc.build())
        while run.k < k and not run.done:
            run.tick()
        self._take(sc, run)

    def _take(self, sc: Scenario, run: NetworkRun) -> None:
        self.scenario, self.run = sc, run
        run.scenario_text = self.scenario_text
        self._tree = cKDTree(run.setup.cells.positions)

    # what the run is now
    @property
    def t(self) -> float:
        """Simulated time now, s (the start of the next tick)."""
        return self.run.k * self.run.period

    @property
    def done(self) -> bool:
        """True once the run has reached its end."""
        return self.run.done

    @property
    def scenario_text(self) -> str:
        """The TOML of the scenario that this run is the run of: the file given when nothing was done, else the
        changed scenario written out."""
        return self.text if not self.actions and self.text is not None else dump_toml(self.scenario)

    def dead(self) -> np.ndarray:
        """(n,) bool: cells dead from now on (including a kill or revival recorded for the next tick)."""
        return dead_cells(self.run.setup, self.t)

    def absent(self) -> np.ndarray:
        """(n,) bool: cells taken out of the array now."""
        return absent_cells(self.run.setup, self.t)

    def waiting(self) -> list[int]:
        """Parcels due on the array by now but not let on yet (their place is taken)."""
        return [i for i in self.run.queue if self.run.arrive[i] <= self.t + 1e-12]

    def delivered(self) -> int:
        """Parcels that came on and have left the array (through an exit or, lost, over an edge)."""
        return sum(1 for e, a in zip(self.run.entered, self.run.active) if e is not None and not a)

    def cell_at(self, x: float, y: float) -> int | None:
        """The cell under (x, y) m, or None when no cell centre is within half a pitch (a cell's own square)."""
        d, c = self._tree.query([x, y])
        return int(c) if d <= 0.5 * math.sqrt(2) * self.run.setup.cells.pitch else None

    def entries(self) -> list[tuple[str, np.ndarray]]:
        """The entries parcels can be dropped at: (label, outline (k, 2) m)."""
        return [(label, poly) for label, colour, poly in sorter_lanes(self.run.setup) if label.startswith("entry")]

    def exits(self) -> int:
        """How many exits the program has (destinations 0 .. exits() - 1)."""
        return sum(1 for label, colour, poly in sorter_lanes(self.run.setup) if label.startswith("exit"))

    # stepping
    def tick(self) -> None:
        """One control tick (does nothing once the run is done)."""
        if self.run.done:
            return
        start = time.perf_counter()
        self.run.tick()
        self.wall += time.perf_counter() - start

    def advance(self, sim_seconds: float, budget: float) -> None:
        """Tick until ``sim_seconds`` more of simulated time have passed or ``budget`` s of real time are spent."""
        goal = self.t + sim_seconds
        start = time.perf_counter()
        while not self.run.done and self.t + 1e-12 < goal and time.perf_counter() - start < budget:
            self.tick()

    def result(self) -> RunResult:
        """Run to the end (if not there yet) and return the run's result, its scenario text the changed scenario."""
        while not self.run.done:
            self.tick()
        self.run.wall = self.wall
        return self.run.result()

    # steering: each change is recorded in the scenario, which is then run afresh up to now
    def _change(self, sc: Scenario, action: dict, replay: bool) -> None:
        """Record ``action``: ``sc`` is the scenario with it. A fault changes nothing before it happens, so the run
        carries on under the new scenario from its own state (a checkpoint's, bit for bit); a parcel more changes
        the run's shapes, so the new scenario's run is made afresh and ticked up to now (``replay``)."""
        if self.run.done:
            raise ValueError(f"the run has ended at t = {self.t:g} s; nothing more can happen in it")
        sc = parse_text(dump_toml(sc), "the changed scenario")  # what the run folder's scenario.toml will read back
        setup = None if replay else sc.build()
        self.actions.append(action)
        try:
            if replay:
                self._make(sc, self.run.k)
            else:
                self._take(sc, carry_on(self.run, setup))
        except Exception:
            self.actions.pop()
            raise

    def toggle(self, cell: int) -> str:
        """Kill ``cell`` when it is alive, revive it when it is dead, from the next tick on; returns ``"kill"`` or
        ``"revive"``."""
        n = self.run.setup.cells.n
        if not 0 <= cell < n:
            raise ValueError(f"no cell {cell}: the array has {n}")
        kill = not self.dead()[cell]
        sc, t = self.scenario, self.t
        faults = sc.faults
        if t == 0:  # no event at t = 0: the cell is listed dead (or not) from the start
            listed = [c for c in faults.dead_cells if c != cell] + ([cell] if kill else [])
            if not kill and cell not in faults.dead_cells:
                raise ValueError(f"cell {cell} is dead from its drawn faults; it cannot be revived at t = 0")
            faults = faults.model_copy(update={"dead_cells": listed})
        else:
            event = FaultEvent(t=t, dead_cells=[cell]) if kill else FaultEvent(t=t, revived_cells=[cell])
            faults = faults.model_copy(update={"events": [*faults.events, event]})
        self._change(sc.model_copy(update={"faults": faults}),
                     {"t": t, "kind": "kill" if kill else "revive", "cell": cell}, replay=t == 0)
        return "kill" if kill else "revive"

    def drop(self, entry: int = 0, destination: int | None = 0, name: str | None = None) -> str:
        """Put a parcel on entry ``entry`` bound for exit ``destination`` now (it waits while its place is taken):
        the size, mass and friction of the scenario's first parcel, placed where the scenario's parcels arriving
        there start, else at the entry's centre. Returns its name."""
        lanes = self.entries()
        if not 0 <= entry < len(lanes):
            raise ValueError(f"no entry {entry}: the scenario has {len(lanes)}")
        if destination is not None and not 0 <= destination < max(1, self.exits()):
            raise ValueError(f"no exit {destination}: the scenario has {self.exits()}")
        sc = self.scenario
        outline = shapely.Polygon(lanes[entry][1])
        there = [p for p in sc.parcels if outline.covers(shapely.Point(p.x, p.y))]
        template = there[0] if there else sc.parcels[0] if sc.parcels else ParcelEntry(length=0.2, width=0.2, mass=1.0)
        x, y = (there[0].x, there[0].y) if there else tuple(np.asarray(outline.centroid.coords[0]))
        taken = {p.name for p in sc.parcels}
        if name is None:
            name = next(f"v{k:02d}" for k in range(len(taken) + 1) if f"v{k:02d}" not in taken)
        if name in taken:
            raise ValueError(f"a parcel is named {name!r} already")
        parcel = template.model_copy(update={"name": name, "x": float(x), "y": float(y), "theta": 0.0, "vx": 0.0,
                                             "vy": 0.0, "omega": 0.0, "t_start": self.t, "destination": destination,
                                             "sequence": None})
        self._change(sc.model_copy(update={"parcels": [*sc.parcels, parcel]}),
                     {"t": self.t, "kind": "drop", "parcel": name, "entry": entry, "destination": destination},
                     replay=True)
        return name

    # what the page draws
    def cell_values(self, colour_by: str) -> np.ndarray | None:
        """(n,) float per cell for ``colour_by`` (:data:`COLOUR_BY`), NaN where there is none; None when the
        program keeps no such thing."""
        run, n = self.run, self.run.setup.cells.n
        if colour_by == "traffic":  # sentences received so far (the page shows their rate)
            return run.per_cell["cell_received"].astype(float)
        state = run.state
        if colour_by == "hop distance":
            dist = state.get("dist") if isinstance(state, dict) else None
            if dist is None or np.ndim(dist) != 2 or len(dist) != n:
                return None
            from virtual_vehicle.cells.sorting import UNREACHABLE

            d = np.where(np.asarray(dist) >= UNREACHABLE, np.inf, np.asarray(dist, float)).min(axis=1)
            return np.where(np.isfinite(d), d, np.nan)
        words = state.values() if isinstance(state, dict) else [state]
        for w in words:
            if isinstance(w, np.ndarray) and w.shape == (n,):
                return w.astype(float)
        return None


def _free_port(host: str) -> int:
    """A port free on ``host`` now (the server binds it right after)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class Viewer:
    """The page's server: a Bokeh server on ``host`` (default 127.0.0.1) at a free port, one signed session id as
    the access token, and the run stepped on the server's own loop (so the page's callbacks and the ticks never
    run at once). ``url`` is the address to open, token included; ``on_done`` is called once with the result when
    the run reaches its end."""

    def __init__(self, live: LiveRun, host: str = "127.0.0.1", port: int | None = None, on_done=None,
                 frame: float = 0.1):
        from bokeh.server.server import Server
        from bokeh.util.token import generate_session_id
        from tornado.ioloop import IOLoop, PeriodicCallback

        self.live = live
        self.playing = True
        self.speed = 1.0  # simulated s per real s; math.inf: as fast as it runs
        self.on_done = on_done
        self.result: RunResult | None = None
        self.message = ""
        self.frame = frame
        self._key = secrets.token_urlsafe(32)
        self.token = generate_session_id(secret_key=self._key.encode(), signed=True)
        self.loop = IOLoop.current()
        for attempt in range(5):
            self.port = _free_port(host) if port is None else port
            try:
                # on loopback the page's own origins only; exposed, the name others reach it by is not known
                # here, so any origin (the signed session token still guards every connection)
                name = f"[{host}]" if ":" in host else host  # an IPv6 address is bracketed in an origin
                origins = ([f"{name}:{self.port}", f"localhost:{self.port}"] if host in LOOPBACK else ["*"])
                self.server = Server({"/": self._page}, io_loop=self.loop, address=host, port=self.port,
                                     allow_websocket_origin=origins,
                                     sign_sessions=True, secret_key=self._key, generate_session_ids=False,
                                     session_token_expiration=24 * 3600)
                break
            except OSError:
                if port is not None or attempt == 4:
                    raise
        self.host = host
        self._last = time.perf_counter()
        self._stepper = PeriodicCallback(self._step, 1000 * frame / 2)

    @property
    def url(self) -> str:
        """The page's address with its access token."""
        shown = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{shown}:{self.port}/?bokeh-session-id={self.token}"

    def start(self) -> None:
        """Start serving and stepping (on the current IOLoop; run it with ``self.loop.start()``)."""
        self.server.start()
        self._stepper.start()

    def stop(self) -> None:
        """Stop stepping and serving."""
        self._stepper.stop()
        self.server.stop()

    def _step(self) -> None:
        now = time.perf_counter()
        elapsed, self._last = now - self._last, now
        if self.playing and not self.live.done:
            budget = 0.6 * self.frame
            self.live.advance(self.speed * min(elapsed, self.frame) if math.isfinite(self.speed) else math.inf,
                              budget)
        self._check_done()

    def _check_done(self) -> None:
        if self.live.done and self.result is None:
            self.result = self.live.result()
            if self.on_done is not None:
                self.message = self.on_done(self.result) or ""

    def step_once(self) -> None:
        """One tick, paused."""
        self.playing = False
        self.live.tick()
        self._check_done()

    def _page(self, doc) -> None:
        _build_page(doc, self)


_EXIT_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd")  # exit k and the parcels bound for it (as the pictures)
_STATE_COLOURS = np.array([(174, 199, 232), (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213),
                           (196, 156, 148), (247, 182, 210), (219, 219, 141), (158, 218, 229), (199, 199, 199)])
_EMPTY = (242, 242, 242)  # a cell with nothing to show: light, so that sensors and parcels stand out on it
_DEAD, _ABSENT = (25, 25, 25), (120, 120, 120)


def _ramp(v: np.ndarray, lo: tuple, hi: tuple) -> np.ndarray:
    """(n, 3) colours from ``lo`` at v = 0 to ``hi`` at v = 1 (NaN: :data:`_EMPTY`)."""
    f = np.clip(np.nan_to_num(v), 0, 1)[:, None]
    rgb = np.asarray(lo) * (1 - f) + np.asarray(hi) * f
    rgb[~np.isfinite(v)] = _EMPTY
    return rgb


class _Raster:
    """The cells as an image: ``ppp`` pixels per pitch, each pixel the cell whose square (0.9 pitch wide) holds it
    or -1 (the gaps between cells), so that a frame is one lookup of (n,) colours however many cells there are."""

    def __init__(self, cells, tree):
        P, pitch = cells.positions, cells.pitch
        self.ppp = int(np.clip(np.sqrt(3e5 / cells.n), 3, 32))  # sharp gaps on a small array, light on a hall
        self.x0, self.y0 = P.min(axis=0) - pitch / 2
        x1, y1 = P.max(axis=0) + pitch / 2
        self.w, self.h = (max(1, int(np.ceil((b - a) / pitch * self.ppp))) for a, b in ((self.x0, x1), (self.y0, y1)))
        self.dw, self.dh = self.w * pitch / self.ppp, self.h * pitch / self.ppp
        gx, gy = np.meshgrid(self.x0 + (np.arange(self.w) + 0.5) * pitch / self.ppp,
                             self.y0 + (np.arange(self.h) + 0.5) * pitch / self.ppp)
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        _, c = tree.query(pts)
        near = np.abs(pts - P[c]).max(axis=1) <= 0.45 * pitch
        self.map = np.where(near, c, -1).reshape(self.h, self.w)

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """(h, w) uint32 RGBA of the (n, 3) cell colours ``rgb`` (gaps transparent)."""
        rgba = np.zeros((len(rgb) + 1, 4), np.uint8)
        rgba[:-1, :3] = np.clip(rgb, 0, 255)
        rgba[:-1, 3] = 255
        return rgba[self.map].view(np.uint32)[..., 0]


def _cell_colours(live: LiveRun, colour_by: str, memory: dict) -> tuple[np.ndarray, str]:
    """(n, 3) colours of the cells and the legend's words for them."""
    n = live.run.setup.cells.n
    v = live.cell_values(colour_by)
    if v is None:
        rgb, note = np.tile(np.asarray(_EMPTY, float), (n, 1)), f"{colour_by}: not kept by this program"
    elif colour_by == "traffic":  # sentences received per simulated second since the last frame
        before, t_before = memory.get("received", (None, None))
        memory["received"] = (v, live.t)
        rate = memory.get("rate", np.zeros(n))
        if before is not None and len(before) == n and live.t > t_before:
            rate = (v - before) / (live.t - t_before)
        elif before is not None and live.t < t_before:
            rate = np.zeros(n)
        memory["rate"] = rate
        # the ramp starts at the common (heartbeat) level of the working cells, their median, so that only those
        # busier than most stand out (the silent dead cells and the edges' fewer neighbours would pull it down)
        working = rate[~(live.dead() | live.absent())]
        low, top = np.percentile(working, (50, 99)) if len(working) else (0.0, 0.0)
        if top > low:
            rgb = _ramp((rate - low) / (top - low), _EMPTY, (230, 120, 20))
            note = f"traffic: white {low:.3g} (the median) .. orange {top:.3g} sentences received per s per cell"
        else:
            rgb = np.tile(np.asarray(_EMPTY, float), (n, 1))
            note = f"traffic: no cell above the median, {low:.3g} sentences received per s"
    elif colour_by == "hop distance":
        top = max(float(np.nanmax(v)) if np.isfinite(v).any() else 1.0, 1.0)
        rgb = _ramp(v / top, (40, 150, 90), (250, 240, 190))
        note = f"hop distance to the nearest exit: green 0 .. pale {top:.0f} hops (grey: no way out)"
    else:
        k = np.nan_to_num(v).astype(np.int64)
        rgb = np.where((k <= 0)[:, None], np.asarray(_EMPTY, float), _STATE_COLOURS[k % len(_STATE_COLOURS)])
        note = ("program state: the program's first per-cell word (sorter: the parcel a cell carries), a colour for "
                "each value above 0")
    rgb[live.absent()] = _ABSENT
    rgb[live.dead()] = _DEAD
    return rgb, note + "; dead cells black, cells taken out grey"


def _parcel_data(live: LiveRun) -> tuple[dict, dict]:
    """The parcels on the array and those due but waiting, as columns for the page's sources."""
    run, setup = live.run, live.run.setup
    dests = [p.destination for p in live.scenario.parcels]
    waiting = set(live.waiting())
    on = {"xs": [], "ys": [], "fill": [], "line": [], "width": [], "x": [], "y": [], "label": []}
    wait = {"xs": [], "ys": [], "x": [], "y": [], "label": []}
    places: dict[tuple, list[str]] = {}
    for i in [*run.on, *sorted(waiting)]:
        spec, y = setup.specs[i], run.ys[i]
        ring = np.asarray(spec.world_polygon(y).exterior.coords)
        colour = "#777777" if dests[i] is None else _EXIT_COLOURS[dests[i] % len(_EXIT_COLOURS)]
        label = spec.name if dests[i] is None else f"{spec.name}→{dests[i]}"
        if i in waiting:  # one label a place, under it (the parcel that holds the place keeps its own)
            wait["xs"].append(ring[:, 0])
            wait["ys"].append(ring[:, 1])
            place = (round(float(y[0]), 6), round(float(ring[:, 1].min()), 6))
            places.setdefault(place, []).append(label)
            continue
        still = math.hypot(y[3], y[4]) < STILL and abs(y[5]) * spec.radius < STILL
        for key, value in (("xs", ring[:, 0]), ("ys", ring[:, 1]), ("fill", colour),
                           ("line", "#d62728" if still else colour), ("width", 3.5 if still else 1.5),
                           ("x", y[0]), ("y", y[1]), ("label", label)):
            on[key].append(value)
    for (x, bottom), labels in places.items():
        wait["x"].append(x)
        wait["y"].append(bottom)
        wait["label"].append(f"{labels[0]} waits" if len(labels) == 1 else f"{len(labels)} wait: {labels[0]}, ...")
    return on, wait


def _build_page(doc, viewer: Viewer) -> None:
    """The page of one browser session: the array, the charts and the controls, refreshed every frame."""
    from bokeh.events import Tap
    from bokeh.layouts import column, row
    from bokeh.models import Button, ColumnDataSource, Div, NumeralTickFormatter, Select, Slider, Toggle
    from bokeh.plotting import figure

    live = viewer.live
    state = {"colour_by": "traffic", "memory": {}, "run": None}
    cells = live.run.setup.cells
    pitch = cells.pitch
    raster = _Raster(cells, live._tree)
    lanes = [(label, colour if colour.startswith("#") else "#595959", poly)  # entries: grey
             for label, colour, poly in sorter_lanes(live.run.setup, _EXIT_COLOURS)]
    lo = np.array([raster.x0, raster.y0]) - pitch
    hi = np.array([raster.x0 + raster.dw, raster.y0 + raster.dh]) + pitch
    for _, _, poly in lanes:
        lo, hi = np.minimum(lo, poly.min(axis=0) - 0.2 * pitch), np.maximum(hi, poly.max(axis=0) + 0.2 * pitch)
    width = 900
    height = int(np.clip(width * (hi[1] - lo[1]) / (hi[0] - lo[0]), 250, 900))
    p = figure(name="array", x_range=tuple(float(v) for v in (lo[0], hi[0])),
               y_range=tuple(float(v) for v in (lo[1], hi[1])), frame_width=width, frame_height=height,
               match_aspect=True, tools="pan,wheel_zoom,reset,save", active_scroll=None, x_axis_label="x (m)",
               y_axis_label="y (m)", title="click a cell to kill or revive it", background_fill_color="white")
    p.grid.visible = False
    image = ColumnDataSource({"image": [raster.image(np.tile(np.asarray(_EMPTY, float), (cells.n, 1)))]},
                             name="cells")
    p.image_rgba(image="image", source=image, x=raster.x0, y=raster.y0, dw=raster.dw, dh=raster.dh)
    for label, colour, poly in lanes:
        p.patch(poly[:, 0], poly[:, 1], fill_alpha=0, line_color=colour, line_width=2.5)
        p.text([poly[:, 0].mean()], [poly[:, 1].max() - 0.15 * pitch], text=[label], text_color=colour,
               text_font_size="12px", text_font_style="bold", text_align="center", text_baseline="top",
               background_fill_color="white", background_fill_alpha=0.85)
    sensors = ColumnDataSource({"x": [], "y": []}, name="sensors")
    waiting = ColumnDataSource({"xs": [], "ys": [], "x": [], "y": [], "label": []}, name="waiting")
    parcels = ColumnDataSource({"xs": [], "ys": [], "fill": [], "line": [], "width": [], "x": [], "y": [],
                                "label": []}, name="parcels")
    p.patches("xs", "ys", source=waiting, fill_color="#d62728", fill_alpha=0.08, line_color="#d62728",
              line_width=2, line_dash="dashed")
    p.patches("xs", "ys", source=parcels, fill_color="fill", fill_alpha=0.45, line_color="line",
              line_width="width")
    p.scatter("x", "y", source=sensors, size=max(3.0, min(7.0, 0.08 * pitch * width / (hi[0] - lo[0]))),
              color="#d62728")
    for src, baseline, colour in ((parcels, "middle", "black"), (waiting, "top", "#d62728")):
        p.text("x", "y", text="label", source=src, text_font_size="12px", text_align="center",
               text_baseline=baseline, text_color=colour, background_fill_color="white",
               background_fill_alpha=0.8)

    charts = []
    series = ColumnDataSource({"t": [], "rtf": [], "left": [], "waiting": [], "on": [], "sentences": []},
                              name="series")
    for title, keys in (("real-time factor (simulated s per s simulating)", (("rtf", "#444444"),)),
                        ("sentences received per simulated s", (("sentences", "#e6781e"),)),
                        ("parcels", (("left", "#2ca02c"), ("on", "#1f77b4"), ("waiting", "#d62728")))):
        c = figure(title=title, width=420, height=190 if len(keys) == 1 else 240, x_axis_label="simulated time (s)",
                   tools="")
        c.yaxis.formatter = NumeralTickFormatter(format="0.[0]a")  # 108k, not 1.08000000001e+5
        c.y_range.start = 0
        for key, colour in keys:
            c.line("t", key, source=series, color=colour, line_width=2, **({"legend_label": key} if len(keys) > 1
                                                                            else {}))
        if len(keys) > 1:  # above the chart, not over its lines
            c.legend.orientation = "horizontal"
            c.legend.label_text_font_size = "11px"
            c.add_layout(c.legend[0], "above")
        charts.append(c)

    status = Div(name="status", text="", styles={"font-family": "monospace", "font-size": "13px"})
    legend = Div(name="legend", text="", width=900, styles={"font-size": "12px", "color": "#333"})
    log = Div(name="actions", text="<b>recorded</b>: nothing yet", width=420,
              styles={"font-family": "monospace", "font-size": "12px"})
    play = Button(name="play", label="pause", button_type="primary", width=80)
    step = Button(name="step", label="one tick", width=80)
    speed = Slider(name="speed", title="speed (log10 of simulated s per real s)", start=math.log10(SPEEDS[0]),
                   end=math.log10(SPEEDS[1]), step=0.1, value=0.0, width=260)
    fast = Toggle(name="fast", label="as fast as it runs", width=140)
    colour = Select(name="colour", title="cells coloured by", value="traffic", options=list(COLOUR_BY), width=160)
    entries = [label for label, _ in live.entries()]
    entry = Select(name="entry", title="drop at", value=entries[0] if entries else "", options=entries, width=110)
    dests = [str(k) for k in range(live.exits())]
    dest = Select(name="destination", title="bound for exit", value=dests[0] if dests else "", options=dests,
                  width=110)
    drop = Button(name="drop", label="drop a parcel", width=110, disabled=not entries)

    def say(text: str) -> None:
        viewer.message = text

    def on_play() -> None:
        viewer.playing = not viewer.playing

    def on_step() -> None:
        viewer.step_once()

    def on_speed(attr, old, new) -> None:
        viewer.speed = math.inf if fast.active else 10 ** new

    def on_fast(active) -> None:
        viewer.speed = math.inf if active else 10 ** speed.value

    def on_colour(attr, old, new) -> None:
        state["colour_by"] = new
        state["memory"] = {}

    def on_drop() -> None:
        try:
            name = live.drop(entries.index(entry.value), int(dest.value) if dests else None)
            say(f"parcel {name} dropped at t = {live.t:g} s")
        except ValueError as exc:
            say(f"not dropped: {exc}")

    def on_tap(event) -> None:
        c = live.cell_at(event.x, event.y)
        if c is None:
            return
        try:
            did = live.toggle(c)
            say(f"cell {c}: {'killed' if did == 'kill' else 'revived'} at t = {live.t:g} s")
        except ValueError as exc:
            say(f"cell {c} unchanged: {exc}")

    play.on_click(on_play)
    step.on_click(on_step)
    speed.on_change("value_throttled", on_speed)
    fast.on_click(on_fast)
    colour.on_change("value", on_colour)
    drop.on_click(on_drop)
    p.on_event(Tap, on_tap)

    def refresh() -> None:
        run = live.run
        if state["run"] is not run:  # made afresh after a change: its counts start over, the rate shown stays
            state["run"] = run
            state["memory"].pop("received", None)
        rgb, note = _cell_colours(live, state["colour_by"], state["memory"])
        image.data = {"image": [raster.image(rgb)]}
        readings = getattr(run, "readings", None)
        if readings is not None:
            lit = run.sensors.points[readings.astype(bool)] if readings.ndim == 2 else np.zeros((0, 2))
            sensors.data = {"x": lit[:, 0], "y": lit[:, 1]}
        on, wait = _parcel_data(live)
        parcels.data, waiting.data = on, wait
        rtf = live.t / live.wall if live.wall > 0 else float("nan")
        n_wait = len(wait["x"])
        last = series.data["t"][-1] if len(series.data["t"]) else -1.0
        if live.t > last:
            heard = float(run.per_cell["cell_received"].sum())
            before, t_before = state.get("heard", (heard, live.t))
            rate = round((heard - before) / (live.t - t_before)) if live.t > t_before and heard >= before else None
            state["heard"] = (heard, live.t)
            series.stream({"t": [live.t], "rtf": [rtf], "left": [live.delivered()], "waiting": [n_wait],
                           "on": [len(on["x"])], "sentences": [rate]}, rollover=5000)
        play.label = "pause" if viewer.playing and not live.done else "play"
        end = live.run.setup.scenario.duration
        status.text = (f"t = {live.t:.2f} s of {end:g} s &nbsp; real-time factor {rtf:.3g} &nbsp; on the array "
                       f"{len(on['x'])} &nbsp; waiting {n_wait} &nbsp; left {live.delivered()} &nbsp; "
                       f"{'ended' if live.done else 'running' if viewer.playing else 'paused'}"
                       + (f"<br>{viewer.message}" if viewer.message else ""))
        legend.text = (f"{note}. Red dots: sensors lit. Parcels coloured by their exit; red thick outline: standing "
                       f"still; red dashed: due but waiting for its place.")
        rows = [f"t={a['t']:g} s: " + (f"{a['kind']} cell {a['cell']}" if a["kind"] != "drop" else
                                       f"drop {a['parcel']} at entry {a['entry']} for exit {a['destination']}")
                for a in live.actions]
        log.text = "<b>recorded</b>: " + ("<br>".join(rows[-12:]) if rows else "nothing yet")

    refresh()
    doc.add_periodic_callback(refresh, int(1000 * viewer.frame))
    controls = row(play, step, speed, fast, colour, entry, dest, drop)
    doc.add_root(column(controls, status, row(p, column(*charts, log)), legend))
    doc.title = f"virtual-vehicle view: {live.scenario.name}"
