"""The ``virtual-vehicle`` command.

Exit codes: 0 success, 2 bad input (the message names the field), 1 an unexpected failure.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from .errors import ScenarioError, VirtualVehicleError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Simulate parcels carried by a distributed actuator array (the Virtual Vehicle).")
err = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)


class _LazyProgress:
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
        if self.bar is not None:
            self.bar.stop()


@app.command()
def run(
    scenario: Optional[str] = typer.Argument(None, help="Scenario TOML file or bundled scenario name (default: the "
                                             "18-cell prototype)."),
    out_dir: Path = typer.Option(Path("results/run"), "--out", "-o", help="Folder for the results."),
    plot: bool = typer.Option(True, help="Write paths.png."),
) -> None:
    """Run a scenario; write trajectories.csv, events.csv, summary.json, scenario.toml and paths.png (and, with
    distributed control, network.csv, cell_traffic.csv and traffic.png)."""
    from .io import write_results
    from .scenario import load_scenario
    from .sim import run as run_setup

    try:
        sc, text = load_scenario(scenario)
        setup = sc.build()
    except VirtualVehicleError as exc:
        _fail(exc)
    bar = _LazyProgress(f"simulating {sc.name}")
    try:
        result = run_setup(setup, progress=bar)
    finally:
        bar.close()
    paths = write_results(result, out_dir, text)
    if plot:
        from .viz import plot_paths, plot_traffic

        paths["plot"] = out_dir / "paths.png"
        plot_paths(result, paths["plot"])
        if result.network is not None:
            paths["traffic_plot"] = out_dir / "traffic.png"
            plot_traffic(result, paths["traffic_plot"])
    s = result.summary()
    out.print(f"[bold]{sc.name}[/bold]: {len(result.parcels)} parcel(s), {sc.duration:g} s simulated in "
              f"{result.wall_time:.3g} s ({s['real_time_factor']:.0f}x real time), {sc.friction.law} friction, "
              f"{s['integrator']} integrator")
    for p in s["parcels"]:
        end = p["end"]
        note = f"tipped at t={p['tipped_at_s']:.4g} s" if p["tipped_at_s"] is not None else "on the array"
        out.print(f"  {p['name']}: end x={end['x']:.4f} m, y={end['y']:.4f} m, theta={end['theta']:.4f} rad, "
                  f"{p['support_changes']} support changes, {note}")
        if p["coulomb_sliding_assumption_violated_at_s"] is not None:
            out.print(f"    note: from t={p['coulomb_sliding_assumption_violated_at_s']:.4g} s the parcel outran a wheel; "
                      "the paper's Coulomb law assumes it never does (use the viscous law, or stick-slip when it lands)")
    if result.network is not None:
        net = s["network"]
        lat = "n/a" if net["latency_mean_s"] is None else f"{net['latency_mean_s'] * 1e3:.1f} ms"
        out.print(f"  network ({net['delivery']}): {net['sentences_sent']} sentences sent, {net['sentences_received']} "
                  f"received, mean latency {lat}, {net['dropped']} dropped, {net['corrupted']} corrupted")
    out.print(f"results written to {out_dir}/: " + ", ".join(sorted(p.name for p in paths.values())))


@app.command()
def scenarios() -> None:
    """List the bundled scenarios."""
    from .scenario import DEFAULT_SCENARIO, bundled_scenarios

    for name, desc in bundled_scenarios().items():
        mark = " (default)" if name == DEFAULT_SCENARIO else ""
        out.print(f"[bold]{name}[/bold]{mark}: {desc}")


@app.command()
def check(scenario: str = typer.Argument(..., help="Scenario TOML file or bundled scenario name.")) -> None:
    """Validate a scenario without running it."""
    from .scenario import load_scenario

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
