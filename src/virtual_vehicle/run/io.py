"""Results out: the run's tables (:mod:`virtual_vehicle.run.tables`) as Parquet and/or CSV, a JSON summary, the
scenario as run and a manifest.

Files are written atomically (to a temporary name in the same folder, then renamed), so an interrupted run never
leaves a half-written file under a final name; ``run.json`` (the manifest) is written last, so a folder without it
holds an unfinished run.

A run folder holds ``trajectories``, ``events`` and, for networked runs, ``network`` and ``cell_traffic``, and
``cells`` when ``[sensors] record = true`` (columns and units: :mod:`virtual_vehicle.run.tables`), each as ``.parquet``
and/or ``.csv``; ``summary.json`` (:meth:`~virtual_vehicle.run.results.RunResult.summary`); ``scenario.toml`` (the
scenario exactly as run, seeds included: ``virtual-vehicle run FOLDER/scenario.toml`` reproduces the run bit for bit on
the same versions); ``run.json``: the versions of this package, Python, numpy, scipy and shapely, the scenario's name
and seeds, and every file written with its size and SHA-256.
"""

from __future__ import annotations

import hashlib
import json
import platform
from pathlib import Path

from virtual_vehicle.config.scenario import dump_toml
from virtual_vehicle.run import tables
from virtual_vehicle.run.files import write_atomic
from virtual_vehicle.run.results import RunResult

FORMATS = ("parquet", "csv")

TABLES = ("trajectories", "events", "network", "cell_traffic", "cells")
"""Every table a run folder may hold (:func:`virtual_vehicle.run.tables.build`)."""
RUN_FILES = frozenset({*(f"{t}.{fmt}" for t in TABLES for fmt in FORMATS), "summary.json", "scenario.toml",
                       "run.json", "paths.png", "traffic.png"})
"""The names of every file a run writes into its folder (the manifest run.json among them)."""


def _ours(name: str) -> bool:
    """A run's file, or the temporary name :func:`write_atomic` wrote one under (``.NAME.XXXX``)."""
    return name in RUN_FILES or (name.startswith(".") and any(name.startswith(f".{f}.") for f in RUN_FILES))


def check_folder(out_dir: str | Path) -> str | None:
    """Why ``out_dir`` cannot be a folder to write into, or None when it can (without touching anything): it must be
    a folder or not exist yet, its first existing parent a folder (not a file)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        return f"{str(out)!r} is a file, not a folder"
    parent = out
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        return f"{str(parent)!r} is a file, so {str(out)!r} cannot be a folder"
    return None


def check_run_folder(out_dir: str | Path, keep: tuple[Path, ...] = ()) -> str | None:
    """Why ``out_dir`` cannot take a run's files, or None when it can (without touching anything): it must be a
    folder or not exist yet (its first existing parent a folder), and be empty, or an earlier run's folder (it has
    that run's manifest run.json), or hold nothing but a run's files (an interrupted run's: those
    :func:`clear_run_folder` removes) and the files in ``keep`` (a checkpoint kept there)."""
    out = Path(out_dir)
    problem = check_folder(out)
    if problem is not None:
        return problem
    if out.is_dir() and not (out / "run.json").is_file():  # an earlier run's folder is known by its manifest
        kept = {Path(k).resolve() for k in keep}
        foreign = sorted(e.name for e in out.iterdir() if not _ours(e.name) and e.resolve() not in kept)
        if foreign:
            shown = ", ".join(repr(n) for n in foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3
                                                               else "")
            return (f"folder {str(out)!r} is not empty and holds no earlier run (no run.json) but other files "
                    f"({shown}); name a new or empty folder, or an earlier run's folder")
    return None


def clear_run_folder(out_dir: str | Path) -> list[str]:
    """Remove an earlier run's files from ``out_dir`` (the names in :data:`RUN_FILES` and the temporary files of an
    interrupted write), so that the folder holds exactly the next run's files; leave everything else. Returns the
    names removed."""
    out = Path(out_dir)
    if not out.is_dir():
        return []
    removed = []
    manifest = out / "run.json"
    if manifest.exists():  # the manifest first: a folder without it holds an unfinished run
        manifest.unlink()
        removed.append(manifest.name)
    for entry in sorted(out.iterdir()):
        if _ours(entry.name) and entry.is_file():
            entry.unlink()
            removed.append(entry.name)
    return removed


def scenario_toml(result: RunResult) -> str:
    """The run's scenario as TOML text: the file it was started from, else its validated model written out (a
    scenario built in code)."""
    if result.scenario_text is not None:
        return result.scenario_text
    return dump_toml(result.setup.scenario)


def write_results(result: RunResult, out_dir: str | Path, scenario_text: str | None = None,
                  formats: tuple[str, ...] = FORMATS, extra: list[Path] = ()) -> dict[str, Path]:
    """Write the run's tables in ``formats`` (``"parquet"``, ``"csv"``), summary.json, scenario.toml (``scenario_text``,
    else :func:`scenario_toml`) and, last, the manifest run.json into ``out_dir`` (listing also the ``extra`` files
    already there, such as plots). Returns the paths written, by kind (``trajectories`` is the first format's file,
    ``trajectories.csv`` etc. name each)."""
    bad = set(formats) - set(FORMATS)
    if bad or not formats:
        raise ValueError(f"formats must be some of {FORMATS}, not {sorted(bad) or 'none'}")
    out = Path(out_dir)
    paths: dict[str, Path] = {}
    for name, table in tables.build(result).items():
        for fmt in formats:
            path = out / f"{name}.{fmt}"
            write_atomic(path, tables.to_parquet(table) if fmt == "parquet" else tables.to_csv(table))
            paths.setdefault(name, path)
            paths[f"{name}.{fmt}"] = path
    paths["summary"] = out / "summary.json"
    write_atomic(paths["summary"], json.dumps(result.summary(), indent=2) + "\n")
    paths["scenario"] = out / "scenario.toml"
    write_atomic(paths["scenario"], scenario_text if scenario_text is not None else scenario_toml(result))
    paths["manifest"] = out / "run.json"
    write_atomic(paths["manifest"], json.dumps(manifest(result, sorted({*paths.values(), *map(Path, extra)} - {paths["manifest"]})),
                                               indent=2) + "\n")
    return paths


def manifest(result: RunResult, files: list[Path]) -> dict:
    """What a run folder needs to be reproduced and checked: versions, scenario name and seeds, files and hashes."""
    import numpy
    import scipy
    import shapely

    from virtual_vehicle import __version__

    sc = result.setup.scenario
    seeds = {"sensors": sc.sensors.seed}
    if sc.control is not None:
        seeds["network"] = sc.control.seed
    return {
        "virtual_vehicle": __version__,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "shapely": shapely.__version__,
        "platform": platform.platform(),
        "scenario": sc.name,
        "seeds": seeds,
        "reproduce": "virtual-vehicle run scenario.toml",
        "files": {p.name: {"bytes": p.stat().st_size, "sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
                  for p in files},
    }
