"""Results out: the run's tables (:mod:`virtual_vehicle.tables`) as Parquet and/or CSV, a JSON summary, the
scenario as run and a manifest.

Files are written atomically (to a temporary name in the same folder, then renamed), so an interrupted run never
leaves a half-written file under a final name; ``run.json`` (the manifest) is written last, so a folder without it
holds an unfinished run.

A run folder holds ``trajectories``, ``events`` and, for networked runs, ``network`` and ``cell_traffic``, and
``cells`` when ``[sensors] record = true`` (columns and units: :mod:`virtual_vehicle.tables`), each as ``.parquet``
and/or ``.csv``; ``summary.json`` (:meth:`~virtual_vehicle.sim.RunResult.summary`); ``scenario.toml`` (the scenario
exactly as run, seeds included: ``virtual-vehicle run FOLDER/scenario.toml`` reproduces the run bit for bit on the
same versions); ``run.json``: the versions of this package, Python, numpy, scipy and shapely, the scenario's name
and seeds, and every file written with its size and SHA-256.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import tempfile
from pathlib import Path

from . import tables
from .sim import RunResult

FORMATS = ("parquet", "csv")


def write_atomic(path: Path, data: str | bytes) -> None:
    """Write ``data`` to ``path`` so that the file appears complete or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = "wb" if isinstance(data, bytes) else "w"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **({} if mode == "wb" else {"encoding": "utf-8", "newline": ""})) as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def scenario_toml(result: RunResult) -> str:
    """The run's scenario as TOML text: the file it was started from, else its validated model written out (a
    scenario built in code)."""
    if result.scenario_text is not None:
        return result.scenario_text
    from .scenario import dump_toml

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

    from . import __version__

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
