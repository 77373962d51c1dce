"""The ``virtual-vehicle`` command.

Exit codes: 0 success, 2 bad input (the message names the field), 1 an unexpected failure, or (``sweep``,
``fault-study``) some runs failed, their table still written; 130 stopped by Ctrl-C (``sweep``, ``fault-study``:
finished runs kept, run again to resume).
"""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from virtual_vehicle.errors import ScenarioError, VirtualVehicleError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  rich_markup_mode=None,  # help texts are plain: "[field]" and "[sensors] record" are TOML, not markup
                  help="Simulate parcels carried by a distributed actuator array (the Virtual Vehicle).")
err = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)


def _version(value: bool) -> None:
    if value:
        from virtual_vehicle import __version__

        out.print(f"virtual-vehicle {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """Simulate parcels carried by a distributed actuator array (the Virtual Vehicle)."""


class Phase:
    """A status line on stderr for a phase of a command that takes longer than ``delay`` seconds: "LABEL ..." once
    it has, "LABEL: done in X s" when it ends (so that a long set-up, build or write shows where it is)."""

    def __init__(self, label: str, delay: float = 1.0):
        self.label = label
        self.delay = delay
        self.shown = False

    def _show(self) -> None:
        self.shown = True
        err.print(f"{self.label} ...", highlight=False, markup=False)

    def __enter__(self):
        import threading

        self.start = time.perf_counter()
        self.timer = threading.Timer(self.delay, self._show)
        self.timer.daemon = True
        if self.delay <= 0:
            self._show()
        else:
            self.timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self.timer.cancel()
        if self.shown and exc[0] is None:
            err.print(f"{self.label}: done in {time.perf_counter() - self.start:.3g} s", highlight=False,
                      markup=False)


class LazyProgress:
    """A progress bar that appears only once a run has taken longer than ``delay`` seconds."""

    def __init__(self, label: str, delay: float = 1.0):
        self.label = label
        self.delay = delay
        self.start = time.perf_counter()
        self.bar: Progress | None = None
        self.task = None

    def __call__(self, fraction: float) -> None:
        if self.bar is None:
            if time.perf_counter() - self.start < self.delay:
                return
            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                                TimeRemainingColumn(), console=err, transient=True)
            self.bar.start()
            self.task = self.bar.add_task(self.label, total=1.0)
        self.bar.update(self.task, completed=min(max(fraction, 0.0), 1.0))

    def close(self) -> None:
        """Take the bar off the screen (when it appeared): the run is over."""
        if self.bar is not None:
            self.bar.stop()


def _compile_if_new() -> None:
    """Compile the event engine before a run is built and timed where this checkout's sources have no compiled code
    yet (the first run after they changed: numba's cache folder is named by their hash,
    :mod:`virtual_vehicle.compiled_cache`), and say so: else the compiling (minutes) is silently counted in the
    building, or in the run's wall time and real-time factor."""
    import os

    folder = os.environ.get("NUMBA_CACHE_DIR")
    if not folder or any(Path(folder).rglob("*.nbi")):
        return
    from virtual_vehicle.run.warm import warm_up

    with Phase("compiling the event engine for these sources (once, after they change)", delay=0.0):
        warm_up()


def _load_engine() -> None:
    """Load the event engine's compiled code from numba's cache (about a second, silently) once the run is built and
    before it is timed: else each kernel's first call loads it inside the run, counted in its wall time and
    real-time factor (the default scenario read "6 s simulated in 0.25 s (24x real time)", of which its simulation
    took some 5 ms). After building, so that a bad scenario fails at once."""
    from virtual_vehicle.run.warm import warm_up

    warm_up()


@app.command()
def run(
    scenario: Optional[str] = typer.Argument(None, help="Scenario TOML file or bundled scenario name (default: the "
                                             "18-cell prototype)."),
    out_dir: Path = typer.Option(Path("results/run"), "--out", "-o", help="Folder for the results."),
    plot: bool = typer.Option(True, help="Write paths.png."),
    checkpoint: Optional[Path] = typer.Option(None, help="Keep the run's state in this file, to "
                                              "resume after an interruption (virtual-vehicle resume)."),
    checkpoint_every: float = typer.Option(60.0, min=1e-6, help="Simulated seconds between checkpoints."),
    formats: list[str] = typer.Option(["parquet", "csv"], "--format", help="Table formats to write (repeat the "
                                      "option for several): parquet, csv."),
    cell_ids: bool = typer.Option(False, "--cell-ids", help="Write each cell's id beside it in paths.png (at most "
                                  "2000 cells)."),
    saturate: bool = typer.Option(False, "--saturate", help="Feed every entry as fast as it accepts (arrivals = "
                                  "\"saturate\"): the sorting summary gives parcels/hour per entry against the "
                                  "kinematic bound."),
) -> None:
    """Run a scenario; write its tables (trajectories, events and, with distributed control, network and
    cell_traffic) as Parquet and CSV, summary.json, scenario.toml, paths.png (traffic.png) and the manifest
    run.json."""
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import run as run_setup

    try:
        formats = _formats(formats)
        _check_out(out_dir, keep=(checkpoint,) if checkpoint is not None else ())
        if checkpoint is not None:
            _check_file_target(checkpoint, "--checkpoint")
        with Phase("reading the scenario"):
            sc, text = load_scenario(scenario)
            if saturate:  # the scenario as run, written as such to scenario.toml
                from virtual_vehicle.config.scenario import dump_toml, parse_text

                text = dump_toml(sc.model_copy(update={"arrivals": "saturate"}))
                sc = parse_text(text)
        _compile_if_new()
        with Phase(f"building {sc.name}"):
            setup = sc.build()
        _load_engine()
    except VirtualVehicleError as exc:
        _fail(exc)
    if cell_ids and plot:
        from virtual_vehicle.ui.viz import MAX_CELL_IDS

        if setup.cells.n > MAX_CELL_IDS:
            _fail(VirtualVehicleError(f"--cell-ids: ids are drawn for at most {MAX_CELL_IDS} cells; this array has "
                                      f"{setup.cells.n}"))
    bar = LazyProgress(f"simulating {sc.name}")
    try:
        result = run_setup(setup, progress=bar, checkpoint=checkpoint,
                           checkpoint_every=checkpoint_every if checkpoint is not None else None, scenario_text=text)
    finally:
        bar.close()
    _report(result, out_dir, plot, text, formats, cell_ids=cell_ids)


@app.command(name="resume")
def resume_cmd(
    checkpoint: Path = typer.Argument(..., help="A checkpoint written by 'run --checkpoint'."),
    out_dir: Path = typer.Option(Path("results/run"), "--out", "-o", help="Folder for the results."),
    plot: bool = typer.Option(True, help="Write paths.png."),
    formats: list[str] = typer.Option(["parquet", "csv"], "--format", help="Table formats to write: parquet, csv."),
) -> None:
    """Continue an interrupted run from its checkpoint; the results are those of an uninterrupted run."""
    from virtual_vehicle.run.sim import resume

    bar = LazyProgress(f"resuming {checkpoint}")
    try:
        formats = _formats(formats)
        _check_out(out_dir, keep=(checkpoint,))
        _compile_if_new()
        _load_engine()
        result = resume(checkpoint, progress=bar)
    except VirtualVehicleError as exc:
        bar.close()
        _fail(exc)
    finally:
        bar.close()
    _report(result, out_dir, plot, result.scenario_text, formats)


def _formats(formats: list[str]) -> tuple[str, ...]:
    from virtual_vehicle.run.io import FORMATS

    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise VirtualVehicleError(f"--format: {', '.join(bad) or 'none given'}; use {' or '.join(FORMATS)}")
    return tuple(dict.fromkeys(formats))


def _check_out(out_dir: Path, keep: tuple[Path, ...] = ()) -> None:
    """Fail (exit 2) before anything runs when ``--out`` cannot take a run's files (see
    :func:`~virtual_vehicle.run.io.check_run_folder`)."""
    from virtual_vehicle.run.io import check_run_folder

    problem = check_run_folder(out_dir, keep)
    if problem is not None:
        raise VirtualVehicleError(f"--out: {problem}")


def _check_out_folder(out_dir: Path, option: str = "--out") -> None:
    """Fail before anything runs when the folder ``option`` names is a file (or a folder under one): see
    :func:`~virtual_vehicle.run.io.check_folder`."""
    from virtual_vehicle.run.io import check_folder

    problem = check_folder(out_dir)
    if problem is not None:
        raise VirtualVehicleError(f"{option}: {problem}")


def _check_file_target(path: Path, option: str) -> None:
    """Fail before anything runs when a file to be written (``option`` names it) is a folder or lies under a file."""
    if path.is_dir():
        raise VirtualVehicleError(f"{option}: {str(path)!r} is a folder; name a file")
    _check_out_folder(path.parent, option)


def _report(result, out_dir: Path, plot: bool, text: str | None, formats: tuple[str, ...],
            cell_ids: bool = False) -> None:
    """Write a run's files (after removing an earlier run's from the folder) and print its summary."""
    from virtual_vehicle.run.io import clear_run_folder, write_results

    sc = result.setup.scenario
    pictures = {}
    clear_run_folder(out_dir)  # a run folder holds exactly one run's files
    if plot:
        from virtual_vehicle.ui.viz import plot_paths, plot_traffic, sorter_lanes

        pictures["plot"] = out_dir / "paths.png"
        with Phase(f"drawing {pictures['plot']}"):
            if sorter_lanes(result.setup):  # a run with entries and exits: drawn as a sorting run
                from virtual_vehicle.ui.viz import plot_sorting

                plot_sorting(result, pictures["plot"], cell_ids=cell_ids)
            else:
                plot_paths(result, pictures["plot"], cell_ids=cell_ids)
        if result.network is not None and result.network.per_tick["sent"].sum() > 0:
            pictures["traffic_plot"] = out_dir / "traffic.png"
            with Phase(f"drawing {pictures['traffic_plot']}"):
                plot_traffic(result, pictures["traffic_plot"])
    with Phase(f"writing the tables to {out_dir}"):
        paths = {**write_results(result, out_dir, text, formats, extra=list(pictures.values())), **pictures}
    s = result.summary()
    out.print(f"[bold]{sc.name}[/bold]: {len(result.parcels)} parcel(s), {sc.duration:g} s simulated in "
              f"{result.wall_time:.3g} s ({s['real_time_factor']:.0f}x real time), {sc.friction.law} friction, "
              f"{s['integrator']} integrator")
    for p in s["parcels"]:
        end = p["end"]
        note = (f"tipped at t={p['tipped_at_s']:.4g} s" if p["tipped_at_s"] is not None else
                "never put on (its place stayed taken)" if p["status"] == "waiting" else "on the array")
        if p.get("outcome") == "delivered":
            left = p["entered_at_s"] + p["delivery_time_s"]
            note = f"left through exit {p['exit']} at t={left:.4g} s" + ("" if p["correct"] else " (wrong exit)")
        out.print(f"  {p['name']}: end x={end['x']:.4f} m, y={end['y']:.4f} m, theta={end['theta']:.4f} rad, "
                  f"{p['support_changes']} support changes, {note}")
        if "final_error_mm" in p:
            when = p["settled_within_5mm_2deg_at_s"]
            out.print(f"    target error {p['final_error_mm']:.2f} mm, {p['final_error_deg']:.2f} deg; "
                      + (f"within 5 mm and 2 deg from t={when:.3g} s" if when is not None else "not settled"))
    if "sorting" in s:
        so = s["sorting"]
        out.print(f"  sorting: {so['correct']} delivered to the right exit, {so['misrouted']} misrouted, {so['lost']} "
                  f"lost, {so['on_array']} still on the array, {so['waiting']} waiting; {so['collisions']} collisions; "
                  f"{so['throughput_per_hour']:.0f} parcels/hour")
    if result.network is not None:
        net = s["network"]
        lat = "n/a" if net["latency_mean_s"] is None else f"{net['latency_mean_s'] * 1e3:.1f} ms"
        out.print(f"  network ({net['delivery']}): {net['sentences_sent']} sentences sent, {net['sentences_received']} "
                  f"received, mean latency {lat}, {net['dropped']} dropped, {net['corrupted']} corrupted")
    out.print(f"results written to {out_dir}/: " + ", ".join(sorted({p.name for p in paths.values()})))
    slide = s["coulomb_sliding"]
    if slide["parcels_violating"]:  # said once, here (the parcels' lines above leave it out)
        late = [f"{p['name']} from t={p['coulomb_sliding_assumption_violated_at_s']:.4g} s" for p in s["parcels"]
                if p["coulomb_sliding_assumption_violated_at_s"] is not None]
        which = "; ".join(late[:5]) + (f"; {len(late) - 5} more" if len(late) > 5 else "")
        err.print(f"[yellow]warning[/yellow]: the Coulomb law's assumption that every wheel slides under the parcel "
                  f"(paper 4.3) failed for {slide['parcels_violating']} of {len(s['parcels'])} parcel(s) "
                  f"({escape(which)}), first at t={slide['first_violation_s']:.4g} s (a parcel outran a wheel by up to "
                  f"{slide['max_reversed_slip_m_per_s']:.3g} m/s): their motion is not physical from then on; use "
                  + escape('[friction] law = "viscous" or "stick_slip"'), highlight=False)


@app.command(name="animate")
def animate_cmd(
    scenario: Optional[str] = typer.Argument(None, help="Scenario TOML file or bundled scenario name (default: the "
                                             "18-cell prototype)."),
    video: Path = typer.Option(Path("results/animation.mp4"), "--out", "-o", help="Video file: .mp4 (a .gif is "
                             "written beside it if no ffmpeg is found) or .gif."),
    fps: float = typer.Option(20.0, help="Frames per second of video, 0.1..120."),
    speed: float = typer.Option(1.0, help="Simulated seconds per second of video."),
    start: Optional[float] = typer.Option(None, help="First simulated time shown (s; default 0)."),
    end: Optional[float] = typer.Option(None, help="Last simulated time shown (s; default the scenario's duration)."),
) -> None:
    """Run a scenario and animate it: wheel commands as arrows, lit sensors, parcels with their names and goals,
    entries and exits outlined, dead cells crossed out, message traffic as a grey heat map. Networked runs are
    recorded for this ([sensors] record = true). At most 20000 frames; Ctrl-C stops cleanly (exit 130) and
    leaves no partial video."""
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.sim import run as run_setup
    from virtual_vehicle.ui.animate import SUFFIXES, AnimationInterrupted, animate, check_request

    try:
        if video.suffix.lower() not in SUFFIXES:
            raise VirtualVehicleError(f"--out: the video must end in {' or '.join(SUFFIXES)}, got {video.name!r}")
        if video.is_dir():
            raise VirtualVehicleError(f"--out: {str(video)!r} is a folder; name the video file")
        _check_out_folder(video.parent)
        sc, text = load_scenario(scenario)
        if sc.control is not None and not sc.sensors.record:
            sc = sc.model_copy(update={"sensors": sc.sensors.model_copy(update={"record": True})})
        duration = sc.duration
        t0, t1 = 0.0 if start is None else start, duration if end is None else end
        if not 0.0 <= t0 < t1 <= duration:
            raise VirtualVehicleError(f"--start/--end: need 0 <= start < end <= {duration:g} s, got {t0:g}..{t1:g}")
        if not speed > 0:
            raise VirtualVehicleError(f"--speed: must be positive (simulated s per s of video), got {speed:g}")
        try:
            frames = check_request(duration, fps, speed, start, end)
        except ValueError as exc:
            raise VirtualVehicleError(f"--{exc}") from None
        setup = sc.build()
    except VirtualVehicleError as exc:
        _fail(exc)
    bar = LazyProgress(f"simulating {sc.name}")
    try:
        result = run_setup(setup, progress=bar, scenario_text=text)
    except KeyboardInterrupt:
        bar.close()
        err.print("interrupted while simulating: nothing written", highlight=False)
        raise typer.Exit(code=130) from None
    finally:
        bar.close()
    bar = LazyProgress(f"drawing {frames} frames of {video.name}", delay=0.0)
    try:
        written = animate(result, video, fps=fps, speed=speed, start=start, end=end, progress=bar)
    except AnimationInterrupted as exc:
        bar.close()
        err.print(f"interrupted after drawing {exc.frames} of {exc.total} frames: no video written (the partial "
                  f"file was removed; {video} is untouched)", highlight=False)
        raise typer.Exit(code=130) from None
    except KeyboardInterrupt:
        bar.close()
        err.print(f"interrupted: no video written ({video} is untouched)", highlight=False)
        raise typer.Exit(code=130) from None
    finally:
        bar.close()
    note = "" if written == video else " (no ffmpeg found, so a GIF)"
    out.print(f"[bold]{sc.name}[/bold]: animation written to {written}{note}")


@app.command(name="view")
def view_cmd(
    scenario: str = typer.Argument(..., help="Scenario TOML file or bundled scenario name (with [control]), or a "
                                   "run folder to replay."),
    out_dir: Path = typer.Option(Path("results/view"), "--out", "-o", help="Folder for the run's results, written "
                                 "when it ends."),
    host: str = typer.Option("127.0.0.1", help="Address to serve the page on; another than 127.0.0.1 exposes it "
                             "to the network (the token still guards it)."),
    port: Optional[int] = typer.Option(None, min=1, max=65535, help="Port (default: a free one)."),
    paused: bool = typer.Option(False, help="Start paused."),
    plot: bool = typer.Option(True, help="Write paths.png with the results."),
    formats: list[str] = typer.Option(["parquet", "csv"], "--format", help="Table formats to write: parquet, csv."),
) -> None:
    """Run a scenario live and watch and steer it in a browser: prints the page's address with its access token.
    Play, pause, one tick, speed; click a cell to kill or revive it, drop a parcel at an entry, give a parcel of a
    pose program a new target. Everything done is recorded: the run folder written when the run ends holds the
    changed scenario, which 'virtual-vehicle run' replays to the same tables. Ctrl-C before the end finishes the run
    and writes it (Ctrl-C again: nothing written, exit 130). Given a run folder, replays it from its tables with a
    time slider (nothing is written)."""
    from virtual_vehicle.ui.view import LOOPBACK, LiveRun, Viewer

    if Path(scenario).is_dir():
        _replay(scenario, host, port, paused)
        return
    try:
        formats = _formats(formats)
        _check_out(out_dir)
        with Phase("building the scenario"):
            live = LiveRun(scenario)
    except VirtualVehicleError as exc:
        _fail(exc)
    except ValueError as exc:
        _fail(VirtualVehicleError(str(exc)))

    def write(result) -> str:
        _report(result, out_dir, plot, result.scenario_text, formats)
        return f"the run has ended: its folder is written to {out_dir}"

    try:
        viewer = Viewer(live, host=host, port=port, on_done=write)
    except OSError as exc:
        _fail(VirtualVehicleError(f"--host/--port: cannot serve on {host}:{port or 'a free port'}: {exc}"))
    viewer.playing = not paused
    viewer.start()
    out.print(f"[bold]{live.scenario.name}[/bold] live at {viewer.url}", highlight=False, soft_wrap=True)
    if host not in LOOPBACK:
        err.print(f"warning: served on {host}, reachable from other machines (with the token)", highlight=False)
    sys.stdout.flush()
    # Ctrl-C stops the loop between two of its callbacks, never inside a tick (a KeyboardInterrupt raised half-way
    # through one would leave the run's state half-stepped, and the folder written would not replay exactly)
    stopped = []

    def on_sigint() -> None:
        stopped.append(True)
        viewer.loop.stop()

    viewer.loop.asyncio_loop.add_signal_handler(signal.SIGINT, on_sigint)
    try:
        viewer.loop.start()
    except KeyboardInterrupt:
        stopped.append(True)
    finally:
        viewer.loop.asyncio_loop.remove_signal_handler(signal.SIGINT)
    if stopped:
        viewer.stop()
        if viewer.result is None:
            err.print(f"stopped at t = {live.t:g} s: finishing the run to write it (Ctrl-C again: nothing written)",
                      highlight=False)
            try:
                write(live.result())
            except KeyboardInterrupt:
                err.print("interrupted: nothing written", highlight=False)
                raise typer.Exit(code=130) from None


def _replay(folder: str, host: str, port: int | None, paused: bool) -> None:
    """Serve the replay of run folder ``folder`` until Ctrl-C."""
    from virtual_vehicle.ui.view import LOOPBACK, Viewer
    from virtual_vehicle.ui.view.replay import Replay

    try:
        with Phase("reading the run folder"):
            replay = Replay(folder)
    except VirtualVehicleError as exc:
        _fail(exc)
    except ValueError as exc:
        _fail(VirtualVehicleError(str(exc)))
    try:
        viewer = Viewer(replay, host=host, port=port)
    except OSError as exc:
        _fail(VirtualVehicleError(f"--host/--port: cannot serve on {host}:{port or 'a free port'}: {exc}"))
    viewer.playing = not paused
    viewer.start()
    out.print(f"[bold]{replay.scenario.name}[/bold] replayed from {folder} at {viewer.url}", highlight=False,
              soft_wrap=True)
    if host not in LOOPBACK:
        err.print(f"warning: served on {host}, reachable from other machines (with the token)", highlight=False)
    sys.stdout.flush()
    viewer.loop.asyncio_loop.add_signal_handler(signal.SIGINT, viewer.loop.stop)
    try:
        viewer.loop.start()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.loop.asyncio_loop.remove_signal_handler(signal.SIGINT)
        viewer.stop()


@app.command(name="layout")
def layout_cmd(
    scenario: Optional[str] = typer.Argument(None, help="Scenario TOML file or bundled scenario name (default: the "
                                             "18-cell prototype)."),
    picture: Path = typer.Option(Path("results/layout.png"), "--out", "-o", help="PNG file to write."),
    cell_ids: bool = typer.Option(True, help="Write each cell's id (at most 2000 cells)."),
) -> None:
    """Draw a scenario's array without running it: every cell with its id (numbered row by row from the bottom row
    up, left to right), entries and exits, dead cells and the parcels where they start."""
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.ui.viz import MAX_CELL_IDS, plot_layout

    try:
        if picture.suffix.lower() != ".png":
            raise VirtualVehicleError(f"--out: the picture must end in .png, got {picture.name!r}")
        _check_file_target(picture, "--out")
        sc, _ = load_scenario(scenario)
        setup = sc.build()
        if cell_ids and setup.cells.n > MAX_CELL_IDS:
            raise VirtualVehicleError(f"--cell-ids: ids are drawn for at most {MAX_CELL_IDS} cells; this array has "
                                      f"{setup.cells.n} (use --no-cell-ids)")
    except VirtualVehicleError as exc:
        _fail(exc)
    picture.parent.mkdir(parents=True, exist_ok=True)
    plot_layout(setup, picture, cell_ids=cell_ids)
    out.print(f"[bold]{sc.name}[/bold]: {setup.cells.n} cells drawn to {picture}")


@app.command()
def sweep(
    spec: Path = typer.Argument(..., help="Sweep file (TOML): base scenario, mode, and the fields to vary."),
    out_dir: Path = typer.Option(Path("results/sweep"), "--out", "-o", help="Folder for runs/ and summary.parquet; "
                                 "run again on the same folder to resume."),
    scheduler: Optional[str] = typer.Option(None, help="Address of a running Dask scheduler (default: a local "
                                            "cluster); it must answer within 5 s."),
    workers: int = typer.Option(2, min=1, max=4096, help="Worker processes of the local cluster."),
    retry_failed: bool = typer.Option(False, "--retry-failed", help="Also run again the runs recorded as failed "
                                      "(status error); runs lost to the cluster are always run again."),
) -> None:
    """Run every variation of a base scenario on Dask and collect their summaries into one Parquet table; failed
    runs are recorded with their error, and an interrupted sweep resumes without redoing finished runs. Exit code 1
    when any run failed (the table is still written), 2 for a bad sweep file (nothing runs), 130 after Ctrl-C."""
    from virtual_vehicle.analysis.sweep import load_sweep, run_sweep

    try:
        sw, base = load_sweep(spec)
        count = len(sw.variations())
        _check_out_folder(out_dir)
    except VirtualVehicleError as exc:
        _fail(exc)
    res = _study(f"sweeping {count} variations of {sw.base}", out_dir,
                 lambda bar: run_sweep(sw, base, out_dir, scheduler=scheduler, workers=workers, progress=bar,
                                       retry_failed=retry_failed))
    out.print(f"[bold]{escape(sw.base)}[/bold]: {res['runs']} runs ({res['ran']} run now, {res['skipped']} already "
              f"done), {res['failed']} failed; summary in {escape(str(res['summary']))}")
    _runs_failed(res)


def _study(label: str, out_dir: Path, call):
    """``call(progress)`` (a sweep or a fault study) under a progress bar: a bad input is one message (exit 2), an
    interrupt says what was kept (exit 130), also before any run started or while the summary is written."""
    from virtual_vehicle.analysis.sweep import SweepInterrupted

    bar = LazyProgress(label, delay=0.0)
    try:
        return call(bar)
    except VirtualVehicleError as exc:
        bar.close()
        _fail(exc)
    except SweepInterrupted as exc:
        bar.close()
        _interrupted(exc)
    except KeyboardInterrupt:
        bar.close()
        _interrupted(None, out_dir)
    finally:
        bar.close()


def _interrupted(exc, out_dir: Path | None = None) -> None:
    """Say what an interrupted sweep (``exc`` a SweepInterrupted, or None and its ``out_dir``) kept and how to
    resume it; exit 130 (as after SIGINT)."""
    kept = (f"{exc.kept} of {exc.runs} runs finished and kept in {escape(str(exc.out / 'runs'))} (each complete; no "
            "summary written)") if exc is not None else f"finished runs are kept in {escape(str(out_dir / 'runs'))}"
    err.print(f"interrupted: {kept}; run the same command again to resume", highlight=False)
    raise typer.Exit(code=130)


def _runs_failed(res: dict) -> None:
    """Exit 1 when some runs of a sweep failed, saying how many and how to retry them."""
    if res["failed"]:
        lost = f" ({res['lost']} lost to the cluster, retried on the next run)" if res["lost"] else ""
        err.print(f"[red]{res['failed']} of {res['runs']} runs failed[/red]{lost}: see the status and error columns "
                  f"of {escape(str(res['summary']))}; run again with --retry-failed to retry them", highlight=False)
        raise typer.Exit(code=1)


@app.command(name="fault-study")
def fault_study_cmd(
    scenario: str = typer.Argument("sorting_junction", help="A sorting scenario (program \"sort\")."),
    kind: str = typer.Option("dead_cell_rate", help="Which failure rate to vary: dead_cell_rate, stuck_wheel_rate, "
                             "free_wheel_rate, dead_link_rate, stuck_sensor_rate."),
    rates: str = typer.Option("0,0.02,0.05,0.1", help="Comma-separated failure rates (probability per item)."),
    samples: int = typer.Option(5, min=1, max=100_000, help="Runs (fault seeds) per rate."),
    duration: Optional[float] = typer.Option(None, help="Simulated seconds per run (default: the scenario's)."),
    out_dir: Path = typer.Option(Path("results/fault_study"), "--out", "-o", help="Folder (resumable sweep)."),
    scheduler: Optional[str] = typer.Option(None, help="Address of a running Dask scheduler."),
    workers: int = typer.Option(2, min=1, max=4096, help="Worker processes of the local cluster."),
    retry_failed: bool = typer.Option(False, "--retry-failed", help="Also run again the runs recorded as failed "
                                      "(status error); runs lost to the cluster are always run again."),
) -> None:
    """Monte-Carlo redundancy study: delivered fraction, delay and collisions against a failure rate, over random
    fault draws; writes study.json, study.png and the sweep's summary.parquet. Exit code 1 when any run failed (the
    study is still written, from the runs that finished), 130 after Ctrl-C (rerun to resume)."""
    import json

    from rich.table import Table

    from virtual_vehicle.analysis.sweep import fault_study
    from virtual_vehicle.ui.viz import plot_fault_study

    try:
        values = [float(x) for x in rates.split(",") if x.strip()]
    except ValueError:
        _fail(VirtualVehicleError(f"--rates: not a list of numbers: {rates!r}"))
    try:
        _check_out_folder(out_dir)
    except VirtualVehicleError as exc:
        _fail(exc)
    rows = _study(f"fault study of {scenario}", out_dir,
                  lambda bar: fault_study(scenario, kind, values, samples, out_dir, duration=duration,
                                          scheduler=scheduler, workers=workers, progress=bar,
                                          retry_failed=retry_failed))
    name = json.loads((out_dir / "study.json").read_text(encoding="utf-8"))["scenario"]  # (a file's: not its path)
    plot_fault_study(rows, kind, f"{name}: {samples} fault draws per rate", out_dir / "study.png")
    table = Table(title=f"{name}: {kind}")
    for head in ("rate", "delivered (mean ± std)", "draws (least .. most)", "delivery time (s)", "collisions",
                 "misrouted", "lost", "failed"):
        table.add_column(head)

    def fmt(v, spec=".3g"):
        return "n/a" if v is None else format(v, spec)

    for r in rows:
        draws = r["draws"]["delivered_fraction"]
        table.add_row(fmt(r["rate"]), f"{fmt(r['delivered_fraction'])} ± {fmt(r['delivered_fraction_std'])}",
                      f"{fmt(min(draws))} .. {fmt(max(draws))}" if draws else "n/a", fmt(r["delivery_time_mean_s"]),
                      fmt(r["collisions"]), fmt(r["misrouted"]), fmt(r["lost"]), str(r["failed"]))
    out.print(table)
    out.print(f"written to {out_dir}/study.json, study.png and summary.parquet")
    _runs_failed({"failed": sum(r["failed"] for r in rows), "lost": 0, "runs": sum(r["runs"] for r in rows),
                  "summary": out_dir / "summary.parquet"})


@app.command(name="scale-study")
def scale_study_cmd(
    scenario: Optional[str] = typer.Argument(None, help="Scenario TOML file or bundled scenario name (with a "
                                             "constant [field]); default the 18-cell prototype."),
    lengths: str = typer.Option("1,0.01,10", help="Comma-separated length factors (the first is the reference)."),
    masses: Optional[str] = typer.Option(None, help="Comma-separated mass factors, one per length factor "
                                         "(default: length factor cubed, as for a solid of one material)."),
    out_dir: Path = typer.Option(Path("results/scale_study"), "--out", "-o", help="Folder for the results."),
) -> None:
    """Scalability: run one scenario from micro to large scale (lengths times s, times and speeds times sqrt(s),
    masses times m) and show that, in units of the pitch and sqrt(pitch / g), the runs are one and the same;
    writes scale_study.json and scale_study.png."""
    import json

    from rich.table import Table

    from virtual_vehicle.analysis.scaling import similarity_study
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.files import write_atomic
    from virtual_vehicle.ui.viz import plot_similarity

    try:
        _check_out_folder(out_dir)
        sc, _ = load_scenario(scenario)
        try:
            ls = [float(x) for x in lengths.split(",") if x.strip()]
            ms = [s ** 3 for s in ls] if masses is None else [float(x) for x in masses.split(",") if x.strip()]
        except ValueError:
            raise VirtualVehicleError(f"--lengths / --masses: not a list of numbers: {lengths!r}, {masses!r}") \
                from None
        if not ls or len(ms) != len(ls):
            raise VirtualVehicleError("--masses: give one mass factor per length factor")
        rows = similarity_study(sc, list(zip(ls, ms)))
    except VirtualVehicleError as exc:
        _fail(exc)
    out_dir.mkdir(parents=True, exist_ok=True)
    plot_similarity(rows, f"{sc.name}: one run at {len(rows)} scales", out_dir / "scale_study.png")
    table = Table(title=f"{sc.name}: Froude-similar family")
    for head in ("length x", "mass x", "pitch (m)", "parcel mass (kg)", "duration (s)", "max dimensionless deviation"):
        table.add_column(head)
    for r in rows:
        table.add_row(f"{r['length_factor']:g}", f"{r['mass_factor']:g}", f"{r['pitch_m']:.3g}",
                      f"{r['mass_kg']:.3g}", f"{r['duration_s']:.3g}", f"{r['max_deviation']:.2e}")
    out.print(table)
    keep = [{k: v for k, v in r.items() if k not in ("tau", "states")} for r in rows]
    write_atomic(out_dir / "scale_study.json", json.dumps({"scenario": sc.name, "runs": keep}, indent=2))
    out.print(f"written to {out_dir}/scale_study.json and scale_study.png")


@app.command(name="equilibria")
def equilibria_cmd(
    scenario: Optional[str] = typer.Argument(None, help="Scenario TOML file or bundled scenario name (with a "
                                             "constant [field])."),
    parcel: Optional[str] = typer.Option(None, help="Parcel name (default: the first)."),
    out_dir: Path = typer.Option(Path("results/equilibria"), "--out", "-o", help="Folder for the results."),
    headings: int = typer.Option(73, min=3, max=100_000, help="Headings sampled over a full turn."),
    step: Optional[float] = typer.Option(None, min=1e-9, help="Spacing (m) of sampled centre-of-mass positions "
                                         "(default: a quarter pitch)."),
) -> None:
    """Find the equilibrium poses a constant field gives a parcel and their stability; write equilibria.json and
    force_field.png (force and torque at the first stable heading, equilibria marked)."""
    import json

    import numpy as np

    from virtual_vehicle.analysis.equilibria import equilibria
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.files import write_atomic
    from virtual_vehicle.ui.viz import plot_force_field

    try:
        _check_out_folder(out_dir)
        sc, _ = load_scenario(scenario)
        setup = sc.build()
        if setup.control is not None:
            raise ScenarioError("field", "equilibria need a constant [field], not [control]")
        names = [s.name for s in setup.specs]
        if parcel is not None and parcel not in names:
            raise ScenarioError("parcel", f"no parcel named {parcel!r}; the scenario has {', '.join(names)}")
    except VirtualVehicleError as exc:
        _fail(exc)
    spec = setup.specs[names.index(parcel) if parcel else 0]
    cells = setup.contact_layer
    eqs = equilibria(cells, spec, setup.contact_velocities, setup.law, headings=np.linspace(0, 2 * np.pi, headings),
                     step=step, gravity=sc.gravity)
    rows = [{"x_m": e.pose[0], "y_m": e.pose[1], "theta_rad": e.pose[2], "translation": e.translation,
             "rotation": e.rotation, "stable": e.stable, "stiffness_N_per_m": e.stiffness.tolist(),
             "torque_below_above_Nm": list(e.torque_jump), "heading_range_rad": e.heading_range,
             "support": list(e.support)} for e in eqs]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(out_dir / "equilibria.json", json.dumps({"scenario": sc.name, "parcel": spec.name,
                                                           "friction_law": sc.friction.law, "equilibria": rows},
                                                          indent=2).encode())
    shown = next((e for e in eqs if e.stable and e.rotation == "stable"), next((e for e in eqs if e.stable), None))
    heading = shown.pose[2] if shown else 0.0

    def at_heading(e):
        lo, hi = e.heading_range or (e.pose[2], e.pose[2])
        return any(lo - 1e-6 <= heading + k * 2 * np.pi <= hi + 1e-6 for k in (-1, 0, 1))

    plot_force_field(cells, spec, setup.contact_velocities, setup.law, heading, [e for e in eqs if at_heading(e)],
                     out_dir / "force_field.png", step=step, gravity=sc.gravity)
    stable = sum(e.stable for e in eqs)
    out.print(f"[bold]{sc.name}[/bold] / {spec.name}: {len(eqs)} equilibria ({stable} stable or neutral); "
              f"written to {out_dir}/equilibria.json and force_field.png")


@app.command()
def compare(
    scenario: str = typer.Argument("sorting_junction", help="A task scenario (program \"sort\" or \"pose\": a "
                                   "program with a task report that also runs centrally)."),
    out_dir: Path = typer.Option(Path("results/compare"), "--out", "-o", help="Folder for compare.json."),
    force: bool = typer.Option(False, "--force", help="Replace an earlier compare.json in the folder."),
) -> None:
    """Run a task scenario with distributed and with central control (a sorting scenario also with the central
    reservation router) and print the metrics side by side; an earlier comparison in the folder is kept unless
    --force is given."""
    import json

    from rich.table import Table

    from virtual_vehicle.analysis.compare import compare as compare_modes
    from virtual_vehicle.cells.programs import PROGRAMS, program_of, with_task
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.files import write_atomic

    try:
        sc, _ = load_scenario(scenario)
        if sc.control is None or not program_of(sc.control).COMPARED or not program_of(sc.control).CENTRAL:
            tasks = " or ".join(f'"{name}"' for name in with_task(PROGRAMS, central=True))
            raise ScenarioError("control.program", f"compare needs a task scenario (program = {tasks})")
        _check_out_folder(out_dir)
        if (out_dir / "compare.json").exists() and not force:
            raise VirtualVehicleError(f"--out: {str(out_dir / 'compare.json')!r} holds an earlier comparison; "
                                      "name another folder, or give --force to replace it")
    except VirtualVehicleError as exc:
        _fail(exc)
    bar = LazyProgress(f"simulating {sc.name} under each control")
    try:
        both = compare_modes(sc, progress=bar)
    finally:
        bar.close()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(out_dir / "compare.json", json.dumps({"scenario": sc.name, **both}, indent=2).encode())
    table = Table(title=f"{sc.name}: {sc.duration:g} s, {len(sc.parcels)} parcels")
    table.add_column("metric")
    for mode in both:
        table.add_column({"reserve": "reservation router"}.get(mode, mode))
    for key, label in program_of(sc.control).COMPARED:
        cells = []
        for mode in both:
            v = both[mode][key]
            cells.append("n/a" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v))
        table.add_row(label, *cells)
    out.print(table)
    out.print(f"written to {out_dir}/compare.json")


@app.command(name="reproduce")
def reproduce_cmd(
    names: Optional[list[str]] = typer.Argument(None, help="Classic results to reproduce (default: all): "
                                                "inward_2x2, row_oscillator, squeeze, elliptic, orientation, "
                                                "realistic_law."),
    out_dir: Path = typer.Option(Path("results/classics"), "--out", "-o", help="Folder for the results (one "
                                 "sub-folder each)."),
) -> None:
    """Reproduce the field's classic results with this package's physics; write each one's figure and table and
    print the source's statement beside ours. Exits 1 when one does not reproduce."""
    from rich.table import Table

    from virtual_vehicle.analysis.classics import CLASSICS, reproduce

    unknown = [n for n in names or () if n not in CLASSICS]
    try:
        if unknown:
            raise VirtualVehicleError(f"no classic result named {', '.join(map(repr, unknown))}; choose from "
                                      f"{', '.join(CLASSICS)}")
        _check_out_folder(out_dir)
    except VirtualVehicleError as exc:
        _fail(exc)
    results = []
    for name in dict.fromkeys(names or CLASSICS):
        with Phase(f"reproducing {name}", delay=0):
            results.extend(reproduce([name], out_dir))
    table = Table(title="classic results", show_lines=True)
    for col in ("name", "source's statement", "ours", "result"):
        table.add_column(col, overflow="fold")
    for r in results:
        table.add_row(r.name, escape(f"{r.statement}\n({r.source})"), escape(r.ours),
                      "[green]reproduced[/green]" if r.passed else "[red]NOT reproduced[/red]")
    out.print(table)
    out.print(f"figures and tables in {out_dir}/NAME/", highlight=False, markup=False)
    if not all(r.passed for r in results):
        raise typer.Exit(code=1)


@app.command()
def scenarios() -> None:
    """List the bundled scenarios."""
    from virtual_vehicle.config.scenario import DEFAULT_SCENARIO, bundled_scenarios

    for name, desc in bundled_scenarios().items():
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        out.print(f"[bold]{name}[/bold]{mark}: {desc}")


@app.command()
def check(scenario: str = typer.Argument(..., help="Scenario TOML file or bundled scenario name.")) -> None:
    """Validate a scenario without running it."""
    from virtual_vehicle.config.scenario import load_scenario

    try:
        sc, _ = load_scenario(scenario)
        setup = sc.build()
    except VirtualVehicleError as exc:
        _fail(exc)
    out.print(f"{sc.name}: valid ({setup.cells.n} cells, {len(setup.specs)} parcel(s))")


def _fail(exc: VirtualVehicleError) -> None:
    kind = "invalid scenario" if isinstance(exc, ScenarioError) else type(exc).__name__
    err.print(f"[red]error[/red] ({kind}): {escape(str(exc))}", highlight=False)
    raise typer.Exit(code=2)


def main() -> None:
    """Console entry point."""
    try:
        app()
    except VirtualVehicleError as exc:  # anything typed that escaped a command
        err.print(f"error: {escape(str(exc))}", highlight=False)
        sys.exit(2)


if __name__ == "__main__":
    main()
