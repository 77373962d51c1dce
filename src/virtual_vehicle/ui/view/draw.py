"""What the live page and the replay page both draw, and how each frame reaches the browser.

:class:`ArrayView` is the array's figure: the cells as one RGBA image layer (a pixel map from pixels to cells built
once, so a frame is one lookup of (n,) colours however many cells there are), the entries and exits, each wheel's
speed as an arrow (on arrays up to :data:`ARROWS_UP_TO` cells; on a hall they would be specks), the lit sensors and
the parcels. A frame sends only what changed: the image as patches of the tiles whose cells changed colour (colours
come in a few steps, so a cell whose value drifts a little keeps its colour and costs nothing), the other sources
only when their data differ. On a 100 x 100 hall that is what keeps the page fluid (``benchmarks/bench_view.py``).
Units: m, m/s.
"""

from __future__ import annotations

import numpy as np

from virtual_vehicle.ui.viz import sorter_lanes

ARROWS_UP_TO = 2500
"""Cells: wheel arrows are drawn on arrays up to this size (on a larger hall an arrow would be a few pixels)."""
TILE = 8
"""Cells along a side of the image's patch tiles: a frame sends the changed part of each tile with a change."""
STEPS = 16
"""Colour steps of a ramp (traffic, hop distance): values that drift within a step do not repaint the cell."""
LABEL_PX = 40
"""Pixels a parcel must span on the page for its name to be written on it (else it is in the hover tooltip)."""
STALL = "#d62728"
"""Outline of a parcel standing still or stalled (and the dashed outline of one waiting for its place)."""

EXIT_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd")  # exit k and the parcels bound for it (as the pictures)
STATE_COLOURS = np.array([(174, 199, 232), (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213),
                           (196, 156, 148), (247, 182, 210), (219, 219, 141), (158, 218, 229), (199, 199, 199)])
EMPTY = (242, 242, 242)  # a cell with nothing to show: light, so that sensors and parcels stand out on it
DEAD, ABSENT = (25, 25, 25), (120, 120, 120)


def ramp(v: np.ndarray, lo: tuple, hi: tuple) -> np.ndarray:
    """(n, 3) colours from ``lo`` at v = 0 to ``hi`` at v = 1 in :data:`STEPS` steps (NaN: :data:`EMPTY`)."""
    f = np.round(np.clip(np.nan_to_num(v), 0, 1) * (STEPS - 1))[:, None] / (STEPS - 1)
    rgb = np.asarray(lo) * (1 - f) + np.asarray(hi) * f
    rgb[~np.isfinite(v)] = EMPTY
    return rgb


class Raster:
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

    @staticmethod
    def colours(rgb: np.ndarray) -> np.ndarray:
        """(n + 1,) uint32 RGBA of the (n, 3) cell colours ``rgb`` and, last, of the gaps (transparent): indexed
        by :attr:`map`, an image."""
        rgba = np.zeros((len(rgb) + 1, 4), np.uint8)
        rgba[:-1, :3] = np.clip(rgb, 0, 255)
        rgba[:-1, 3] = 255
        return rgba.view(np.uint32)[:, 0]

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """(h, w) uint32 RGBA of the (n, 3) cell colours ``rgb`` (gaps transparent)."""
        return self.colours(rgb)[self.map]


def _bounds(setup, raster: Raster, lanes) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners (m) of what the figure shows: the cells and the lanes, with a margin."""
    pitch = setup.cells.pitch
    lo = np.array([raster.x0, raster.y0]) - pitch
    hi = np.array([raster.x0 + raster.dw, raster.y0 + raster.dh]) + pitch
    for _, _, poly in lanes:
        lo, hi = np.minimum(lo, poly.min(axis=0) - 0.2 * pitch), np.maximum(hi, poly.max(axis=0) + 0.2 * pitch)
    return lo, hi


def _same(a: dict, b: dict) -> bool:
    """True when two sources' column dicts hold the same values (arrays compared by value)."""
    if a.keys() != b.keys():
        return False
    for k in a:
        x, y = a[k], b[k]
        if len(x) != len(y):
            return False
        for u, v in zip(x, y):
            if isinstance(u, np.ndarray) or isinstance(v, np.ndarray):
                if not np.array_equal(u, v):
                    return False
            elif u != v:
                return False
    return True


class ArrayView:
    """The array's Bokeh figure (``figure``) and its sources, updated frame by frame with :meth:`show`.

    Args:
        setup: the run's setup (cells, lanes, sensors).
        tree: a KD-tree of the cells' centres (m).
        title: the figure's title.
        send_all: replace every source each frame instead of sending what changed (the way the page worked
            before; kept to measure the difference, see ``benchmarks/bench_view.py``).
    """

    def __init__(self, setup, tree, title: str, width: int = 900, send_all: bool = False):
        from bokeh.models import Arrow, ColumnDataSource, HoverTool, VeeHead
        from bokeh.plotting import figure

        cells = setup.cells
        self.setup, self.send_all = setup, send_all
        pitch = cells.pitch
        self.raster = raster = Raster(cells, tree)
        self.lanes = [(label, colour if colour.startswith("#") else "#595959", poly)  # entries: grey
                      for label, colour, poly in sorter_lanes(setup, EXIT_COLOURS)]
        lo, hi = _bounds(setup, raster, self.lanes)
        height = int(np.clip(width * (hi[1] - lo[1]) / (hi[0] - lo[0]), 250, 900))
        p = figure(name="array", x_range=tuple(float(v) for v in (lo[0], hi[0])),
                   y_range=tuple(float(v) for v in (lo[1], hi[1])), frame_width=width, frame_height=height,
                   match_aspect=True, tools="pan,wheel_zoom,reset,save", active_scroll=None, x_axis_label="x (m)",
                   y_axis_label="y (m)", title=title, background_fill_color="white")
        p.grid.visible = False
        self.rgb = np.tile(np.asarray(EMPTY, np.uint8), (cells.n, 1))
        self.pixels = raster.image(self.rgb)
        self.image = ColumnDataSource({"image": [self.pixels]}, name="cells")
        p.image_rgba(image="image", source=self.image, x=raster.x0, y=raster.y0, dw=raster.dw, dh=raster.dh)
        for label, colour, poly in self.lanes:
            p.patch(poly[:, 0], poly[:, 1], fill_alpha=0, line_color=colour, line_width=2.5)
            p.text([poly[:, 0].mean()], [poly[:, 1].max() - 0.15 * pitch], text=[label], text_color=colour,
                   text_font_size="12px", text_font_style="bold", text_align="center", text_baseline="top",
                   background_fill_color="white", background_fill_alpha=0.85)
        self.arrows_on = cells.n <= ARROWS_UP_TO
        self.arrows = ColumnDataSource({"x0": [], "y0": [], "x1": [], "y1": []}, name="wheels")
        self._speed_top = 0.0
        if self.arrows_on:
            head = max(3.0, min(7.0, 0.12 * pitch * width / (hi[0] - lo[0])))
            p.add_layout(Arrow(end=VeeHead(size=head, line_color="#3b5b92", line_width=1.2), x_start="x0",
                               y_start="y0", x_end="x1", y_end="y1", source=self.arrows, line_color="#3b5b92",
                               line_width=1.2, line_alpha=0.8))
        self.sensors = ColumnDataSource({"x": [], "y": []}, name="sensors")
        self.waiting = ColumnDataSource({"xs": [], "ys": [], "x": [], "y": [], "label": []}, name="waiting")
        self.parcels = ColumnDataSource({"xs": [], "ys": [], "fill": [], "line": [], "width": [], "x": [], "y": [],
                                         "label": []}, name="parcels")
        p.patches("xs", "ys", source=self.waiting, fill_color=STALL, fill_alpha=0.08, line_color=STALL,
                  line_width=2, line_dash="dashed")
        shapes = p.patches("xs", "ys", source=self.parcels, fill_color="fill", fill_alpha=0.45, line_color="line",
                           line_width="width")
        p.add_tools(HoverTool(renderers=[shapes], tooltips=[("parcel", "@label")]))
        p.scatter("x", "y", source=self.sensors, size=max(1.5, min(7.0, 0.08 * pitch * width / (hi[0] - lo[0]))),
                  color=STALL)
        # a label wider than its parcel would hide its neighbours' (a hall): there the names are in the tooltips
        sizes = [max(s.polygon.bounds[2] - s.polygon.bounds[0], s.polygon.bounds[3] - s.polygon.bounds[1])
                 for s in setup.specs]
        self.labels_on = not sizes or float(np.median(sizes)) * width / (hi[0] - lo[0]) >= LABEL_PX
        for src, baseline, colour in ((self.parcels, "middle", "black"), (self.waiting, "top", STALL)):
            p.text("x", "y", text="label", source=src, text_font_size="12px", text_align="center",
                   text_baseline=baseline, text_color=colour, background_fill_color="white",
                   background_fill_alpha=0.8, visible=self.labels_on)
        self.figure = p

    def show(self, rgb: np.ndarray, lit: np.ndarray, wheels: np.ndarray | None, on: dict, wait: dict) -> None:
        """Draw one frame: ``rgb`` (n, 3) cell colours, ``lit`` (k, 2) m the lit sensors' points, ``wheels``
        (n, 2) m/s each wheel's surface speed along its drive direction (None: not known), ``on`` and ``wait`` the
        columns of the parcels on the array and of those waiting for their place."""
        self._show_cells(np.clip(np.rint(rgb), 0, 255).astype(np.uint8))
        self.set_source(self.sensors, {"x": lit[:, 0], "y": lit[:, 1]})
        if self.arrows_on:
            self.set_source(self.arrows, self._arrow_data(wheels))
        self.set_source(self.parcels, on)
        self.set_source(self.waiting, wait)

    def set_source(self, source, data: dict) -> None:
        """Give ``source`` (one of the page's, drawn on this figure) ``data``, sent only when it differs."""
        if self.send_all or not _same(source.data, data):
            source.data = data

    def _show_cells(self, rgb: np.ndarray) -> None:
        """Repaint the cells whose colour changed: the changed block of each tile with a change, as one patch."""
        changed = np.any(rgb != self.rgb, axis=1)
        self.rgb = rgb
        raster = self.raster
        if self.send_all:
            self.pixels = raster.image(rgb)
            self.image.data = {"image": [self.pixels]}
            return
        if not changed.any():
            return
        rgba = raster.colours(rgb)
        mask = np.append(changed, False)[raster.map]  # the gaps (-1) never change
        side = TILE * raster.ppp
        H, W = -(-raster.h // side), -(-raster.w // side)
        padded = np.zeros((H * side, W * side), bool)
        padded[:raster.h, :raster.w] = mask
        patches = []
        for r, c in zip(*np.nonzero(padded.reshape(H, side, W, side).any(axis=(1, 3)))):
            block = mask[r * side:(r + 1) * side, c * side:(c + 1) * side]
            rows, cols = np.flatnonzero(block.any(axis=1)), np.flatnonzero(block.any(axis=0))
            rs = slice(r * side + rows[0], r * side + rows[-1] + 1)
            cs = slice(c * side + cols[0], c * side + cols[-1] + 1)
            patches.append(((0, rs, cs), rgba[raster.map[rs, cs]]))
        self.image.patch({"image": patches})  # Bokeh applies it to the server's copy (self.pixels) too

    def _arrow_data(self, wheels: np.ndarray | None) -> dict:
        """Arrow ends: from each cell's centre along each wheel's drive direction, the fastest wheel seen so far
        0.45 pitch long (a fixed scale, so arrows can be compared from frame to frame)."""
        if wheels is None:
            return {"x0": [], "y0": [], "x1": [], "y1": []}
        cells = self.setup.cells
        self._speed_top = max(self._speed_top, float(np.abs(wheels).max(initial=0.0)))
        moving = np.abs(wheels) > 1e-9 * max(self._speed_top, 1e-300)
        i, k = np.nonzero(moving)
        start = cells.positions[i]
        end = start + cells.drive_directions[i, k] * (wheels[i, k] / self._speed_top * 0.45 * cells.pitch)[:, None]
        return {"x0": start[:, 0], "y0": start[:, 1], "x1": end[:, 0], "y1": end[:, 1]}


def place_labels(wait: dict, places: dict[tuple, list[tuple[str, np.ndarray]]]) -> None:
    """Fill ``wait``'s columns from ``places``: (x, bottom) m of a place where parcels due queue -> (label, outline
    ring (k, 2) m) of each parcel waiting there. One row per parcel (so the columns have one length); the place's
    label (under it) on its first parcel's row, empty on the others'."""
    for (x, bottom), queue in places.items():
        labels = [label for label, _ in queue]
        for k, (_, ring) in enumerate(queue):
            wait["xs"].append(ring[:, 0])
            wait["ys"].append(ring[:, 1])
            wait["x"].append(x)
            wait["y"].append(bottom)
            wait["label"].append("" if k else f"{labels[0]} waits" if len(labels) == 1 else
                                 f"{len(labels)} wait: {labels[0]}, ...")
