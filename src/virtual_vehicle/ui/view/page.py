"""The live page: the cells as one image layer (coloured by traffic, the program's state or the hop distance to
the nearest exit; dead cells black, cells taken out dark grey), lit sensors, entries and exits, the parcels
(outlines, names, destinations; those due but not yet let on, and those standing still, outlined in red), and live
charts of the real-time factor, the sentences received per second and the parcels that left the array (delivered),
are on it and wait, against simulated time, with the controls that steer the run. Units: m, s.
"""

from __future__ import annotations

import math

import numpy as np

from virtual_vehicle.ui.view.draw import (ABSENT, ARROWS_UP_TO, DEAD, EMPTY, EXIT_COLOURS, STALL, STATE_COLOURS,
                                          ArrayView, place_labels, ramp)
from virtual_vehicle.ui.view.live import COLOUR_BY, STILL, LiveRun


SPEEDS = (0.1, 10.0)
"""The range of simulated seconds per real second the page's speed slider sets (``math.inf``: as fast as it
runs)."""
TRAFFIC_WINDOW = 1.0
"""s: the cells' traffic is shown as sentences received per s over this much simulated time (a heartbeat's
worth by default: a shorter window flickers with each cell's heartbeat, and every flicker is a cell to resend)."""


def _sticky(memory: dict, key: str, value: float, factor: float = 1.25) -> float:
    """``value``, or the one kept under ``key`` while ``value`` stays within ``factor`` of it."""
    kept = memory.get(key)
    if kept is None or not (kept / factor <= value <= kept * factor) and abs(value - kept) > 1e-9:
        memory[key] = kept = value
    return kept


def _cell_colours(live: LiveRun, colour_by: str, memory: dict) -> tuple[np.ndarray, str]:
    """(n, 3) colours of the cells and the legend's words for them."""
    n = live.run.setup.cells.n
    v = live.cell_values(colour_by)
    if v is None:
        rgb, note = np.tile(np.asarray(EMPTY, float), (n, 1)), f"{colour_by}: not kept by this program"
    elif colour_by == "traffic":  # sentences received per simulated second over the last TRAFFIC_WINDOW s
        history = memory.setdefault("received", [])  # (t, counts) at the frames of the window
        if history and (len(history[-1][1]) != n or live.t < history[-1][0]):
            history.clear()  # the run was made afresh: its counts start over
        history.append((live.t, v))
        while len(history) > 2 and history[1][0] <= live.t - TRAFFIC_WINDOW:
            history.pop(0)
        (t0, v0), span = history[0], live.t - history[0][0]
        # a page opened on a run under way has one frame yet: the mean since the start until it has two
        rate = (v - v0) / span if span > 0 else v / live.t if live.t > 0 else np.zeros(n)
        # the ramp starts at the common (heartbeat) level of the working cells, their median, so that only those
        # busier than most stand out (the silent dead cells and the edges' fewer neighbours would pull it down);
        # its ends move only when the levels move by a quarter, so that cells keep their colours from frame to frame
        working = rate[~(live.dead() | live.absent())]
        low, top = np.percentile(working, (50, 99)) if len(working) else (0.0, 0.0)
        low, top = _sticky(memory, "low", low), _sticky(memory, "top", top)
        if top > low:
            rgb = ramp((rate - low) / (top - low), EMPTY, (230, 120, 20))
            over = f"over the last {min(span, TRAFFIC_WINDOW):.2g} s" if span > 0 else "since the start"
            note = (f"traffic {over}: white {low:.3g} (about the median) .. orange "
                    f"{top:.3g} sentences received per s per cell")
        else:
            rgb = np.tile(np.asarray(EMPTY, float), (n, 1))
            note = f"traffic: no cell above the median, {low:.3g} sentences received per s"
    elif colour_by == "hop distance":
        top = max(float(np.nanmax(v)) if np.isfinite(v).any() else 1.0, 1.0)
        rgb = ramp(v / top, (40, 150, 90), (250, 240, 190))
        note = f"hop distance to the nearest exit: green 0 .. pale {top:.0f} hops (grey: no way out)"
    else:
        k = np.nan_to_num(v).astype(np.int64)
        rgb = np.where((k <= 0)[:, None], np.asarray(EMPTY, float), STATE_COLOURS[k % len(STATE_COLOURS)])
        note = ("program state: the program's first per-cell word (sorter: the parcel a cell carries), a colour for "
                "each value above 0")
    rgb[live.absent()] = ABSENT
    rgb[live.dead()] = DEAD
    return rgb, note + "; dead cells black, cells taken out grey"


def _parcel_data(live: LiveRun, stalled: dict[str, str]) -> tuple[dict, dict]:
    """The parcels on the array and those due but waiting, as columns for the page's sources; ``stalled`` names
    the parcels in a stall now and its kind (:meth:`LiveRun.stalls`): outlined thickest in red, the kind named."""
    run, setup = live.run, live.run.setup
    dests = [p.destination for p in live.scenario.parcels]
    waiting = set(live.waiting())
    on = {"xs": [], "ys": [], "fill": [], "line": [], "width": [], "x": [], "y": [], "label": []}
    wait = {"xs": [], "ys": [], "x": [], "y": [], "label": []}
    places: dict[tuple, list] = {}
    for i in [*run.on, *sorted(waiting)]:
        spec, y = setup.specs[i], run.ys[i]
        ring = np.asarray(spec.world_polygon(y).exterior.coords)
        colour = "#777777" if dests[i] is None else EXIT_COLOURS[dests[i] % len(EXIT_COLOURS)]
        label = spec.name if dests[i] is None else f"{spec.name}→{dests[i]}"
        if i in waiting:  # one label a place, under it (the parcel that holds the place keeps its own)
            place = (round(float(y[0]), 6), round(float(ring[:, 1].min()), 6))
            places.setdefault(place, []).append((label, ring))
            continue
        still = math.hypot(y[3], y[4]) < STILL and abs(y[5]) * spec.radius < STILL
        kind = stalled.get(spec.name)
        for key, value in (("xs", ring[:, 0]), ("ys", ring[:, 1]), ("fill", colour),
                           ("line", STALL if still or kind else colour),
                           ("width", 4.5 if kind else 2.5 if still else 1.5),
                           ("x", y[0]), ("y", y[1]), ("label", f"{label} {kind}" if kind else label)):
            on[key].append(value)
    place_labels(wait, places)
    return on, wait


def _said(action: dict) -> str:
    """One recorded action in the page's log."""
    if action["kind"] == "drop":
        return f"drop {action['parcel']} at entry {action['entry']} for exit {action['destination']}"
    if action["kind"] == "target":
        x, y, th = action["target"]
        return f"target {action['parcel']} ({x:.3f} m, {y:.3f} m, {math.degrees(th):.0f} deg)"
    return f"{action['kind']} cell {action['cell']}"


def build(doc, viewer, send_all: bool = False):
    """Lay out the page of one browser session on ``doc`` (the array, the charts and the controls) for ``viewer``
    (the :class:`~virtual_vehicle.ui.view.server.Viewer` serving it; not imported here, since the server imports this
    module) and return its refresh: the function that draws a frame (called every ``viewer.frame`` s; ``send_all``:
    see :class:`~virtual_vehicle.ui.view.draw.ArrayView`)."""
    from bokeh.events import Tap
    from bokeh.layouts import column, row
    from bokeh.models import Button, ColumnDataSource, Div, NumeralTickFormatter, Select, Slider, Spinner, Toggle
    from bokeh.plotting import figure

    live = viewer.live
    state = {"colour_by": "traffic", "memory": {}, "run": None}
    view = ArrayView(live.run.setup, live._tree, "click a cell to kill or revive it", send_all=send_all)
    p = view.figure

    charts = []
    series = ColumnDataSource({"t": [], "rtf": [], "left": [], "waiting": [], "on": [], "sentences": []},
                              name="series")
    for title, keys in (("real-time factor (simulated s per s simulating)", (("rtf", "#444444"),)),
                        ("sentences received per simulated s", (("sentences", "#e6781e"),)),
                        ("parcels", (("left", "#2ca02c"), ("on", "#1f77b4"), ("waiting", "#d62728")))):
        c = figure(title=title, width=420, height=190 if len(keys) == 1 else 240, x_axis_label="simulated time (s)",
                   tools="")
        c.yaxis.formatter = NumeralTickFormatter(format="0.[00]a")  # 108k, not 1.08000000001e+5; 0.15, not 0.1 twice
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
    for widget in (entry, dest, drop):
        widget.visible = bool(entries)  # a program without entries (pose) takes no dropped parcels
    posed = live.targets() is not None  # a pose program: its parcels' targets can be moved by a click
    names = [s.name for s in live.run.setup.specs] if posed else []
    aim = Select(name="target parcel", title="new target for", value=names[0] if names else "", options=names,
                 width=110, visible=posed)
    heading = Spinner(name="target heading", title="heading (deg)", value=0.0, step=5.0, width=100, visible=posed)
    aiming = Toggle(name="aim", label="click sets its target", width=150, visible=posed)
    targets = ColumnDataSource({"xs": [], "ys": [], "x": [], "y": [], "label": []}, name="targets")
    if posed:  # dotted outlines where the parcels are driven to, named
        p.patches("xs", "ys", source=targets, fill_alpha=0, line_color="#555555", line_width=1.5, line_dash="dotted")
        p.title.text = "click a cell to kill or revive it (or, switched on, to set the chosen parcel's target there)"
        p.text("x", "y", text="label", source=targets, text_font_size="11px", text_align="center",
               text_baseline="top", text_color="#555555", visible=view.labels_on)

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
        if aiming.active:
            pose = (event.x, event.y, math.radians(heading.value or 0.0))
            try:
                live.retarget(aim.value, pose)
                say(f"parcel {aim.value}: new target ({event.x:.3f} m, {event.y:.3f} m, {heading.value or 0:g} deg) "
                    f"at t = {live.t:g} s")
            except ValueError as exc:
                say(f"target unchanged: {exc}")
            return
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
        readings = getattr(run, "readings", None)
        lit = run.sensors.points[readings.astype(bool)] if readings is not None and readings.ndim == 2 else \
            np.zeros((0, 2))
        stalls = live.stalls()
        on, wait = _parcel_data(live, {name: s["kind"] for s in stalls for name in s["parcels"]})
        view.show(rgb, lit, getattr(run, "wheels", None), on, wait)
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
                       + "".join(f"<br>{st['kind']} since t = {st['t_s']:.1f} s: {', '.join(st['parcels'])}"
                                 for st in stalls[:5])
                       + (f"<br>{viewer.message}" if viewer.message else ""))
        arrows = ("Blue arrows: each wheel's speed along its drive direction (the fastest yet: 0.45 pitch). "
                  if view.arrows_on else f"Wheel arrows are drawn on arrays up to {ARROWS_UP_TO} cells. ")
        hints = "" if view.labels_on else "Parcels' names and destinations: hover over them. "
        if posed:
            hints += ("Grey dotted: where each parcel is driven to (switch on 'click sets its target' and click the "
                      "array to move the chosen parcel's). ")
        legend.text = (f"{note}. {arrows}{hints}Red dots: sensors lit. Parcels coloured by their exit; red outline: "
                       f"standing still, thickest and named: stalled longer than the program's wait bound "
                       f"(deadlock: near others stalled, waiting on each other; waiting: alone); red dashed: due but "
                       f"waiting for its place.")
        if posed:
            specs = {spec.name: spec for spec in live.run.setup.specs}
            rings = {k: np.asarray(specs[k].world_polygon(pose).exterior.coords) for k, pose in live.targets().items()}
            view.set_source(targets, {"xs": [r[:, 0] for r in rings.values()], "ys": [r[:, 1] for r in rings.values()],
                                      "x": [pose[0] for pose in live.targets().values()],
                                      "y": [r[:, 1].min() for r in rings.values()],  # under it, off the parcel
                                      "label": [f"{k} target" for k in rings]})
        rows = [f"t={a['t']:g} s: " + _said(a) for a in live.actions]
        log.text = "<b>recorded</b>: " + ("<br>".join(rows[-12:]) if rows else "nothing yet")

    refresh()
    doc.add_periodic_callback(refresh, int(1000 * viewer.frame))
    controls = row(play, step, speed, fast, colour, entry, dest, drop, aim, heading, aiming)
    doc.add_root(column(controls, status, row(p, column(*charts, log)), legend))
    doc.title = f"virtual-vehicle view: {live.scenario.name}"
    return refresh
