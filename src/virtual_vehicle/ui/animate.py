"""Animations of a run: MP4 through the ffmpeg that the ``imageio-ffmpeg`` package ships (or one on the PATH), GIF
(Pillow) when no ffmpeg is found or when the file name asks for it.

Each frame shows the array as cell outlines coloured by message traffic (sentences each cell received per second over
the last ``window`` s; networked runs), every wheel's commanded surface velocity as an arrow along its drive
direction, every presence sensor (lit = covered), and the parcels with their names, destinations (sorting) or
target outlines (pose control). Lengths in m, times in s.

A networked run is animated from its cell log, so run it with ``[sensors] record = true``
(``virtual-vehicle animate`` does this for you); a constant-field run needs nothing more: its wheels hold the
field and its sensors are computed from the parcels' poses (noise-free).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FFMpegWriter, FuncAnimation, PillowWriter  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.colors import LinearSegmentedColormap  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Polygon as PolygonPatch  # noqa: E402

from virtual_vehicle.cells.programs import program_of  # noqa: E402
from virtual_vehicle.model.layout import cell_outlines  # noqa: E402
from virtual_vehicle.run.interrupt import Interrupts, without_sigint  # noqa: E402
from virtual_vehicle.run.results import RunResult  # noqa: E402
from virtual_vehicle.ui.viz import absent_cells, dead_cells, legend_below, sorter_lanes  # noqa: E402

SUFFIXES = (".mp4", ".gif")
FPS_RANGE = (0.1, 120.0)
"""Frames per second of video that :func:`animate` accepts (beyond 120 no player shows the frames)."""
MAX_FRAMES = 20_000
"""Most frames :func:`animate` draws (about 17 minutes of video at 20 fps, and about as many minutes of drawing);
ask for fewer with a higher ``speed``, a lower ``fps`` or a shorter ``start``..``end``."""


class AnimationInterrupted(KeyboardInterrupt):
    """The animation was interrupted (Ctrl-C, SIGTERM) after ``frames`` of ``total`` frames; nothing was written
    (the partial file was removed)."""

    def __init__(self, frames: int, total: int):
        super().__init__(f"interrupted after {frames} of {total} frames")
        self.frames, self.total = frames, total


def frame_count(duration: float, fps: float, speed: float, start: float | None = None,
                end: float | None = None) -> int:
    """Frames an animation of ``start``..``end`` (s, default 0..``duration``) at ``fps`` and ``speed`` draws."""
    t0 = 0.0 if start is None else float(start)
    t1 = duration if end is None else float(end)
    return max(2, int(np.floor((t1 - t0) / speed * fps + 1e-9)) + 1)


def check_request(duration: float, fps: float, speed: float, start: float | None = None,
                  end: float | None = None) -> int:
    """Check an animation request against :data:`FPS_RANGE`, the run's ``duration`` (s) and :data:`MAX_FRAMES`;
    return the frame count. Raises ValueError naming the option that is out of range."""
    if not FPS_RANGE[0] <= fps <= FPS_RANGE[1]:
        raise ValueError(f"fps: {fps:g} frames per second is outside {FPS_RANGE[0]:g}..{FPS_RANGE[1]:g}")
    if not speed > 0:
        raise ValueError("speed must be positive")
    t0 = 0.0 if start is None else float(start)
    t1 = duration if end is None else float(end)
    if not 0.0 <= t0 < t1 <= duration:
        raise ValueError(f"need 0 <= start < end <= {duration:g} s (the run's duration), got {t0:g}..{t1:g}")
    count = frame_count(duration, fps, speed, start, end)
    if count > MAX_FRAMES:
        raise ValueError(f"fps: {t1 - t0:g} s at speed {speed:g} and {fps:g} fps is {count} frames, more than "
                         f"{MAX_FRAMES}; raise --speed, lower --fps or shorten --start/--end")
    return count
TRAFFIC_CMAP = LinearSegmentedColormap.from_list("traffic", ["#f4f4f4", "#d9d9d9", "#8c8c8c"])
"""Light grey to mid grey: no parcel, arrow or sensor colour is drowned by it."""
_DEST_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")


def ffmpeg_exe() -> str | None:
    """The ffmpeg to encode MP4 with: the one bundled by ``imageio-ffmpeg``, else one on the PATH, else None."""
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError, OSError):
        return shutil.which("ffmpeg")


@dataclass(frozen=True)
class FrameData:
    """What each frame shows, as arrays over the frames' times (F frames, n cells, S sensors, m contacts).

    ``times`` (F,) s; ``wheel_speeds`` (F, n, 2) commanded surface speed of each cell's wheels along their drive
    directions, m/s; ``lit`` (F, n, S) sensors covered (as read, for networked runs); ``traffic`` (F, n) sentences
    received per second over the trailing window, or None without a network; ``poses`` (F, P, 3) each parcel's
    x, y (m), theta (rad), NaN while it is not on the array; ``window`` the traffic averaging span, s."""

    times: np.ndarray
    wheel_speeds: np.ndarray
    lit: np.ndarray
    traffic: np.ndarray | None
    poses: np.ndarray
    window: float


def frame_data(result: RunResult, times, window: float = 0.5) -> FrameData:
    """Sample ``result`` at ``times`` (s) for an animation (see :class:`FrameData`); ``window`` (s) is the span over
    which message traffic is averaged. Raises ValueError for a networked run without a cell log."""
    setup = result.setup
    times = np.asarray(times, dtype=float)
    if times.ndim != 1 or len(times) == 0 or not np.all(np.isfinite(times)):
        raise ValueError("times must be a non-empty 1-D array of finite seconds")
    if not window > 0:
        raise ValueError(f"window must be a positive number of seconds, got {window}")
    poses = np.full((len(times), len(result.parcels), 3), np.nan)
    for k, pr in enumerate(result.parcels):
        tr = pr.trajectory
        if pr.entered_at is None:
            continue
        shown = (times >= tr.times[0]) & ((times <= tr.times[-1]) | (tr.status == "tipped"))
        for j in range(3):
            poses[shown, k, j] = np.interp(times[shown], tr.times, tr.states[:, j])
    cells = setup.cells
    log = result.cell_log
    if log is None and setup.control is None:
        speeds = np.einsum("ij,ikj->ik", setup.velocities, cells.drive_directions)
        wheel_speeds = np.broadcast_to(speeds, (len(times), cells.n, 2))
        lit = np.stack([setup.sensors.covered(setup.specs, np.nan_to_num(poses[f]),
                                              active=~np.isnan(poses[f, :, 0])) for f in range(len(times))])
        return FrameData(times, wheel_speeds, lit, None, poses, window)
    if log is None:
        raise ValueError("a networked run is animated from its cell log: run it with [sensors] record = true")
    tick = np.clip(np.searchsorted(log.t, times, side="right") - 1, 0, len(log.t) - 1)
    period = setup.control.period if setup.control is not None else \
        float(np.median(np.diff(log.t))) if len(log.t) > 1 else window
    ticks = max(1, int(round(window / period)))
    csum = np.concatenate([np.zeros((1, cells.n)), np.cumsum(log.received, axis=0)])
    lo = np.maximum(tick + 1 - ticks, 0)
    traffic = (csum[tick + 1] - csum[lo]) / ((tick + 1 - lo)[:, None] * period)
    return FrameData(times, log.commands[tick], log.readings[tick], traffic, poses, ticks * period)


def animate(result: RunResult, path: str | Path, *, fps: float = 20.0, speed: float = 1.0,
            start: float | None = None, end: float | None = None, window: float = 0.5, dpi: int = 100,
            targets=None, progress: Callable[[float], None] | None = None) -> Path:
    """Write an animation of ``result`` to ``path`` (.mp4 or .gif) and return the path written: the .gif beside it
    when an MP4 was asked for and no ffmpeg is found (with a warning). ``fps`` frames per second of video,
    ``speed`` simulated seconds per second of video, ``start``/``end`` the simulated span (s, default the whole
    run), ``window`` (s) the traffic averaging span, ``targets`` (P, 3) target poses to outline (default: those of
    a pose-control scenario); ``progress`` is called with the fraction of frames drawn, after each frame.
    ``fps`` must lie in :data:`FPS_RANGE` and the animation may have at most :data:`MAX_FRAMES` frames
    (ValueError otherwise, see :func:`check_request`). The file appears whole or not at all: it is written under a
    hidden ``.NAME.*.part.mp4`` name and renamed when done; interrupted (Ctrl-C, SIGTERM), the partial file is
    removed and :class:`AnimationInterrupted` (a KeyboardInterrupt) says how many frames were drawn."""
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"animation file must end in {' or '.join(SUFFIXES)}, got {path.name!r}")
    if not (fps > 0 and speed > 0):
        raise ValueError("fps and speed must be positive")
    duration = result.setup.scenario.duration
    count = check_request(duration, fps, speed, start, end)
    t0 = 0.0 if start is None else float(start)
    t1 = duration if end is None else float(end)
    times = t0 + np.arange(count) * speed / fps
    data = frame_data(result, times[times <= t1 + 1e-12], window)
    writer = None
    if path.suffix.lower() == ".mp4":
        exe = ffmpeg_exe()
        if exe is None:
            warnings.warn("no ffmpeg found (install imageio-ffmpeg); writing a GIF instead", stacklevel=2)
            path = path.with_suffix(".gif")
        else:
            matplotlib.rcParams["animation.ffmpeg_path"] = exe
            writer = _Encoder(fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p"])
    if writer is None:
        writer = PillowWriter(fps=fps)
    fig, update = scene(result, data, targets)
    total = len(data.times)
    drawn = [0]

    def draw(f):
        stop.check()  # a Ctrl-C whose KeyboardInterrupt a finaliser swallowed still stops here
        out = update(f)
        drawn[0] = f + 1
        return out

    anim = FuncAnimation(fig, draw, frames=total, blit=False, repeat=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    # written under a hidden temporary name beside the target, renamed when whole, removed on any failure
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".part" + path.suffix, dir=path.parent)
    os.close(fd)
    # ffmpeg's complaints go to matplotlib's log; hold them, to show them only when they are news (not a Ctrl-C)
    held = _HeldLog(logging.getLogger("matplotlib.animation"))
    stop = Interrupts(terminate=True)  # SIGTERM interrupts as Ctrl-C does, so the partial file is removed
    try:
        with stop:
            anim.save(tmp, writer=writer, dpi=dpi,
                      progress_callback=None if progress is None else (lambda i, n: progress((i + 1) / n)))
            os.replace(tmp, path)
    except BaseException as exc:  # after a signal, any error (ffmpeg gone, a broken pipe) is the interrupt's doing
        if stop.seen or _interrupted(exc):
            held.drop()
            raise AnimationInterrupted(drawn[0], total) from None
        raise
    finally:
        held.pass_on()
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


class _HeldLog(logging.Handler):
    """Holds the records of ``logger`` (and keeps them from its parents) until :meth:`pass_on` passes them on;
    :meth:`drop` forgets them. (Not ``release``: that is the lock method ``Handler.handle`` calls after each record,
    which once made this pass every record on at once.)"""

    def __init__(self, logger: logging.Logger):
        super().__init__()
        self.logger, self.records, self.propagate = logger, [], logger.propagate
        logger.addHandler(self)
        logger.propagate = False

    def emit(self, record):
        self.records.append(record)

    def drop(self):
        self.records = []

    def pass_on(self):
        self.logger.removeHandler(self)
        self.logger.propagate = self.propagate
        for record in self.records:
            self.logger.handle(record)
        self.records = []


class _Encoder(FFMpegWriter):
    """matplotlib's ffmpeg writer whose ffmpeg ignores SIGINT: a terminal's Ctrl-C reaches the whole process group,
    and an ffmpeg that died of it first would leave this process a broken pipe instead of the interrupt; this process
    stops and closes ffmpeg itself."""

    def setup(self, *args, **kwargs):
        with without_sigint():  # the disposition is inherited across fork and exec
            super().setup(*args, **kwargs)


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is, or arose while handling, a KeyboardInterrupt."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__context__
    return False


def traffic_range(data: FrameData) -> tuple[float, float]:
    """The span (sentences per s) the traffic colours cover: the 1st to the 99th percentile of every cell's traffic
    over every frame, so that a few busy cells do not wash the rest out and the common level is near white;
    (0, 0) without traffic."""
    if data.traffic is None or not np.any(data.traffic > 0):
        return 0.0, 0.0
    lo, hi = (float(v) for v in np.percentile(data.traffic, [1.0, 99.0]))
    if hi <= lo:  # uniform traffic: show it against zero
        lo, hi = 0.0, float(data.traffic.max())
    return lo, hi


def scene(result: RunResult, data: FrameData, targets=None):
    """The figure and the function that draws frame ``f`` of ``data`` into it (``targets``: see :func:`animate`)."""
    setup = result.setup
    sc = setup.scenario
    cells = setup.cells
    pitch = cells.pitch
    xmin, ymin, xmax, ymax = cells.bounds
    for k, pr in enumerate(result.parcels):  # parcels may stick out of the array (entering, leaving)
        seen = data.poses[:, k, :2][np.isfinite(data.poses[:, k, 0])]
        if len(seen):
            r = pr.spec.radius - pitch
            xmin, ymin = min(xmin, seen[:, 0].min() - r), min(ymin, seen[:, 1].min() - r)
            xmax, ymax = max(xmax, seen[:, 0].max() + r), max(ymax, seen[:, 1].max() + r)
    span = max(xmax - xmin, ymax - ymin, pitch)
    width_in = 8.0
    height_in = float(np.clip(width_in * (ymax - ymin + 2 * pitch) / (xmax - xmin + 2 * pitch), 3.5, 9.0)) + 1.2
    fig, ax = plt.subplots(figsize=(width_in, 2 * round(height_in * 50) / 100))  # even pixel count for H.264
    # the cells: squares (hexagons, belts) along their drive directions, coloured by traffic on a light ramp that
    # starts at the common (heartbeat) level, so that parcels, arrows and sensors stay visible on top
    outlines = cell_outlines(cells, setup.contact_layer, 0.94)
    tiles = PolyCollection(outlines, edgecolors="0.75", linewidths=0.5, zorder=1)
    lo, hi = traffic_range(data)
    if hi > lo:
        tiles.set_cmap(TRAFFIC_CMAP)
        tiles.set_clim(lo, hi)
        tiles.set_alpha(0.6)
        tiles.set_array(data.traffic[0])
        fig.colorbar(tiles, ax=ax, shrink=0.8, pad=0.02, extend="both" if lo > 0 else "max",
                     label=f"sentences received per s per cell\n(mean over the last {data.window:g} s; "
                           f"colours span the 1st..99th percentile)")
    else:
        tiles.set_facecolor("0.96")
    ax.add_collection(tiles)
    # dead cells (faults) and cells taken out (reconfiguration): dark fill and a white X, frame by frame
    dead_tiles = PolyCollection(outlines, facecolors="none", edgecolors="none", zorder=4)
    ax.add_collection(dead_tiles)
    crosses = ax.scatter(cells.positions[:, 0], cells.positions[:, 1], marker="x", s=float(np.clip(
        1200.0 * pitch / max(xmax - xmin, ymax - ymin, pitch), 8.0, 60.0)), linewidths=1.5, c="none", zorder=4,
        gid="dead-cells")
    # the entries and exits of a program that has them (the sorter), outlined and named
    for label, colour, poly in sorter_lanes(setup, _DEST_COLOURS):
        ax.add_patch(PolygonPatch(poly, closed=True, fill=False, ec=colour, lw=2.2, ls="-", zorder=2))
        ax.text(poly[:, 0].mean(), poly[:, 1].mean(), label, ha="center", va="center", fontsize=8, color=colour,
                fontweight="bold", zorder=2, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.75))
    # wheel arrows: one per wheel along its drive direction, from the wheel's contact point
    layer = setup.contact_layer
    origin, direction, owner, wheel = [], [], [], []
    for j in range(layer.n):
        for k in range(2):
            if layer.wheel_active[j, k]:
                origin.append(layer.positions[j])
                direction.append(layer.drive_directions[j, k])
                owner.append(layer.cell_of[j])
                wheel.append(k)
    origin, direction = np.array(origin), np.array(direction)
    owner, wheel = np.array(owner), np.array(wheel)
    top_speed = float(np.abs(data.wheel_speeds).max())
    scale = 0.45 * pitch / top_speed if top_speed > 0 else 0.0

    def arrows(f):
        s = data.wheel_speeds[f][owner, wheel] * scale
        return direction[:, 0] * s, direction[:, 1] * s

    u, v = arrows(0)
    quiver = ax.quiver(origin[:, 0], origin[:, 1], u, v, angles="xy", scale_units="xy", scale=1, minlength=0, color="navy",
                       width=0.0035 * min(1.0, 12 * pitch / span) + 0.0015, zorder=3)
    # sensors
    pts = setup.sensors.points.reshape(-1, 2)
    dots = ax.scatter(pts[:, 0], pts[:, 1], s=float(np.clip(300.0 * pitch / span, 3.0, 30.0)),
                      c=_lit_colours(data.lit[0]), edgecolors="none", zorder=6)
    # parcels
    names = [pr.spec.name for pr in result.parcels]
    marks = program_of(sc.control).markers(setup) if sc.control is not None else None
    dests = marks.destinations if marks is not None else None
    if targets is None and marks is not None:
        targets = marks.targets
    colours = [_DEST_COLOURS[(d or 0) % len(_DEST_COLOURS)] for d in dests] if dests else \
        [_DEST_COLOURS[k % len(_DEST_COLOURS)] for k in range(len(names))]
    if targets is not None:
        for k, tgt in enumerate(targets):
            goal = result.parcels[k].spec.world_polygon(tgt)
            ax.add_patch(PolygonPatch(np.asarray(goal.exterior.coords), closed=True, fill=False, ls=":", ec=colours[k],
                                      lw=1.3, zorder=2))
    patches, labels = [], []
    fontsize = float(np.clip(160 * pitch / span, 6, 10))
    for k, name in enumerate(names):
        patch = PolygonPatch(np.zeros((4, 2)), closed=True, fc=colours[k], alpha=0.55, ec=colours[k], lw=2.0,
                             zorder=5, visible=False)
        ax.add_patch(patch)
        patches.append(patch)
        text = name if dests is None or dests[k] is None else f"{name}→{dests[k]}"
        labels.append(ax.text(0, 0, text, ha="center", va="center", fontsize=fontsize, zorder=7, visible=False,
                              clip_on=True, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.7)))
    legend = [Line2D([], [], color="navy", lw=1.5, label="wheel command"),
              Line2D([], [], ls="none", marker="o", color="crimson", label="sensor lit"),
              Line2D([], [], ls="none", marker="o", color="0.7", label="sensor dark")]
    if dead_cells(setup).any():
        legend.append(Line2D([], [], ls="none", marker="s", ms=9, color="0.1", label="dead cell (white X)"))
    if absent_cells(setup).any():
        legend.append(Line2D([], [], ls="none", marker="s", ms=9, color="0.45", label="cell taken out"))
    if any(True for _ in sorter_lanes(setup, _DEST_COLOURS)):
        legend.append(Line2D([], [], color="0.3", lw=2.2, label="entry / exit k (outline)"))
    if dests:
        legend += [Line2D([], [], ls="none", marker="s", color=_DEST_COLOURS[d % len(_DEST_COLOURS)], alpha=0.5,
                          label=f"parcel→exit {d}") for d in sorted({d for d in dests if d is not None})]
    if targets is not None:
        legend.append(Line2D([], [], ls=":", color="0.2", label="target pose"))
    legend_below(ax, legend, [h.get_label() for h in legend], ncol=min(3, len(legend)))
    if top_speed > 0:
        ax.quiverkey(quiver, 0.9, 1.02, top_speed * scale, f"{top_speed:.3g} m/s", labelpos="W", coordinates="axes",
                     fontproperties={"size": 8})
    ax.set_xlim(xmin - pitch, xmax + pitch)
    ax.set_ylim(ymin - pitch, ymax + pitch)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    title = ax.set_title("")
    fig.tight_layout()

    def update(f):
        if hi > lo:
            tiles.set_array(data.traffic[f])
        t = float(data.times[f])
        dead, out = dead_cells(setup, t), absent_cells(setup, t)
        face = np.zeros((cells.n, 4))
        face[out] = (0.45, 0.45, 0.45, 0.9)
        face[dead] = (0.1, 0.1, 0.1, 0.85)
        dead_tiles.set_facecolors(face)
        mark = np.zeros((cells.n, 4))
        mark[dead] = (1.0, 1.0, 1.0, 1.0)
        crosses.set_edgecolors(mark)
        crosses.set_facecolors(mark)
        quiver.set_UVC(*arrows(f))
        dots.set_facecolors(_lit_colours(data.lit[f]))
        for k, pr in enumerate(result.parcels):
            pose = data.poses[f, k]
            on = bool(np.all(np.isfinite(pose)))
            patches[k].set_visible(on)
            labels[k].set_visible(on)
            if on:
                patches[k].set_xy(np.asarray(pr.spec.world_polygon(pose).exterior.coords))
                labels[k].set_position(pose[:2])
                tipped = pr.trajectory.status == "tipped" and data.times[f] >= pr.trajectory.t_end
                patches[k].set_edgecolor("red" if tipped else colours[k])
        title.set_text(f"{sc.name}   t = {data.times[f]:.2f} s")
        return []

    update(0)
    return fig, update


def _lit_colours(lit: np.ndarray) -> np.ndarray:
    """RGBA per sensor: crimson when lit, light grey when dark."""
    flat = lit.reshape(-1)
    out = np.tile(np.array([0.6, 0.6, 0.6, 0.55]), (len(flat), 1))
    out[flat] = (0.86, 0.08, 0.24, 1.0)
    return out
