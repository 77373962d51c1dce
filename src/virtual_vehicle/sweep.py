"""Parameter sweeps over scenario variations, run on Dask (a local cluster by default, or an existing one).

A sweep file (TOML) names a base scenario and the fields to vary, by dotted path into the scenario's tables
(``"control.loss_rate"``, ``"parcels.0.mass"``, ``"parcels.*.mu"`` for every parcel)::

    base = "sorting_junction"       # bundled name, or a scenario file relative to the sweep file
    mode = "grid"                   # "grid": every combination | "random": ``samples`` draws
    samples = 20                    # random mode
    seed = 0                        # random mode: the draws
    [vary]
    "control.loss_rate" = [0.0, 0.05, 0.1]             # values (grid), or values to pick from (random)
    "duration" = {min = 10.0, max = 20.0}               # random mode: uniform in [min, max]
    "control.seed" = {min = 0, max = 9, integer = true} # random mode: a uniform integer

Every variation runs in its own task; a finished run is written at once to ``runs/<id>.json`` in the output folder
(``id`` a hash of the variation, so a resumed sweep redoes only what is missing and an edited sweep never reuses a
result that is not its own). A variation that is invalid or fails is recorded with its error and the rest go on.
At the end every row is collected into ``summary.parquet`` (and ``summary.csv``): the varied values as columns
``vary.<path>``, ``status`` (``"ok"`` / ``"error"``), ``error``, and the run summary's scalars flattened to dotted
names (``sorting.correct``, ``network.sentences_sent``, ...; units as in ``summary.json``: SI), with
``parcels.tipped`` and, for runs of at most 10 parcels, each parcel's as ``parcel.<name>.<key>``
(``parcel.box.end.x``, ``parcel.box.path_length_m``, ...).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import time
import tomllib
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .errors import ScenarioError, VirtualVehicleError

Scalar = Union[bool, int, float, str]
PER_PARCEL_COLUMNS = 10
"""Runs with at most this many parcels also get each parcel's summary scalars as ``parcel.<name>.<key>``."""


class _Range(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    min: float
    max: float
    integer: bool = False


class SweepSpec(BaseModel):
    """A sweep: the ``base`` scenario, the ``mode`` (``"grid"`` or ``"random"``), ``samples`` and ``seed`` of a
    random sweep, and ``vary``: dotted scenario paths mapped to a list of values or (random mode) a
    {min, max, integer} range."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    base: Annotated[str, Field(min_length=1)]
    mode: Literal["grid", "random"] = "grid"
    samples: Annotated[int, Field(ge=1, le=1_000_000)] = 10
    seed: Annotated[int, Field(ge=0)] = 0
    vary: Annotated[dict[str, Union[Annotated[list[Scalar], Field(min_length=1)], _Range]], Field(min_length=1)]

    def variations(self) -> list[dict[str, Scalar]]:
        """Every variation as {path: value}, in a fixed order (random mode: drawn from ``seed``)."""
        if self.mode == "grid":
            ranges = [k for k, v in self.vary.items() if isinstance(v, _Range)]
            if ranges:
                raise ScenarioError(f"vary.{ranges[0]}", "a grid sweep takes lists of values; ranges are for "
                                    "mode = \"random\"")
            keys = list(self.vary)
            return [dict(zip(keys, combo)) for combo in itertools.product(*(self.vary[k] for k in keys))]
        rng = np.random.default_rng(self.seed)
        out = []
        for _ in range(self.samples):
            row = {}
            for key, v in self.vary.items():
                if isinstance(v, _Range):
                    if v.max < v.min:
                        raise ScenarioError(f"vary.{key}", f"min {v.min} is above max {v.max}")
                    row[key] = int(rng.integers(int(np.ceil(v.min)), int(np.floor(v.max)) + 1)) if v.integer \
                        else float(rng.uniform(v.min, v.max))
                else:
                    row[key] = v[int(rng.integers(len(v)))]
            out.append(row)
        return out


def load_sweep(path: str | Path) -> tuple[SweepSpec, dict]:
    """Read and validate a sweep file; returns the spec and the base scenario's raw tables. Raises ScenarioError."""
    from .scenario import load_scenario

    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError("", f"cannot read sweep file {str(path)!r}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError("", f"{path} is not valid TOML: {exc}") from None
    try:
        spec = SweepSpec.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise ScenarioError(where, err["msg"]) from None
    base = spec.base
    if (path.parent / base).is_file():
        base = str(path.parent / base)
    _, text = load_scenario(base)
    return spec, tomllib.loads(text)


def apply(base: dict, variation: dict[str, Scalar]) -> dict:
    """A copy of the raw scenario tables ``base`` with each dotted path of ``variation`` set (``*`` = every item of
    a list). Raises ScenarioError for a path that leads nowhere."""
    data = copy.deepcopy(base)
    for path, value in variation.items():
        _set(data, path.split("."), value, path)
    return data


def _set(node, keys: list[str], value, path: str) -> None:
    key, rest = keys[0], keys[1:]
    if isinstance(node, list):
        if key == "*":
            if rest:
                for item in node:
                    _set(item, rest, value, path)
            else:
                node[:] = [value] * len(node)
            return
        if not key.isdigit() or int(key) >= len(node):
            raise ScenarioError(path, f"{key!r} is not an index of a list of {len(node)}")
        if rest:
            _set(node[int(key)], rest, value, path)
        else:
            node[int(key)] = value
        return
    if not isinstance(node, dict):
        raise ScenarioError(path, f"cannot go into {key!r}: the value above it is not a table")
    if rest:
        _set(node.setdefault(key, {}), rest, value, path)
    else:
        node[key] = value


def run_id(variation: dict) -> str:
    """A short stable id of a variation (12 hex digits of a SHA-256 of its JSON)."""
    return hashlib.sha256(json.dumps(variation, sort_keys=True).encode()).hexdigest()[:12]


def flatten(summary: dict, prefix: str = "") -> dict:
    """The scalars of a nested summary under dotted names (lists, such as the per-parcel rows, are left out)."""
    out = {}
    for k, v in summary.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, name + "."))
        elif isinstance(v, (bool, int, float, str)) or v is None:
            out[name] = v
    return out


def run_variation(base: dict, variation: dict) -> dict:
    """Run one variation; returns its row (never raises: an invalid or failing run is a row with its error)."""
    from .scenario import parse_scenario
    from .sim import run

    row = {"id": run_id(variation), **{f"vary.{k}": v for k, v in variation.items()}}
    start = time.perf_counter()
    try:
        result = run(parse_scenario(apply(base, variation)).build())
        summary = result.summary()
        row.update(status="ok", error=None, **flatten(summary))
        parcels = summary["parcels"]
        row["parcels.tipped"] = sum(p["tipped_at_s"] is not None for p in parcels)
        if len(parcels) <= PER_PARCEL_COLUMNS:
            for p in parcels:
                row.update(flatten(p, f"parcel.{p['name']}."))
    except VirtualVehicleError as exc:
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    except Exception as exc:  # noqa: BLE001 -- a sweep records any failure and goes on
        row.update(status="error", error=f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=5)}")
    row["sweep_wall_time_s"] = time.perf_counter() - start
    return row


def run_sweep(spec: SweepSpec, base: dict, out_dir: str | Path, *, scheduler: str | None = None,
              workers: int | None = None, progress: Callable[[float], None] | None = None) -> dict:
    """Run every variation of ``spec`` not already in ``out_dir/runs`` on Dask (``scheduler`` the address of a
    running scheduler; default a local cluster of ``workers`` processes, one thread each), writing each row as it
    finishes, then ``summary.parquet`` and ``summary.csv`` of all rows. Returns counts: ``runs``, ``ran``,
    ``skipped`` (finished before), ``failed``, and ``summary`` (the Parquet path)."""
    from dask.distributed import Client, LocalCluster, as_completed

    from .io import write_atomic

    out = Path(out_dir)
    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    variations = spec.variations()
    ids = [run_id(v) for v in variations]
    todo = [(i, v) for i, v in zip(ids, variations) if not (runs_dir / f"{i}.json").is_file()]
    done = len(variations) - len(todo)
    if todo:
        cluster = None
        if scheduler is None:
            cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        client = Client(scheduler if scheduler is not None else cluster)
        try:
            base_future = client.scatter(base, broadcast=True)
            futures = {client.submit(run_variation, base_future, v, pure=False): (i, v) for i, v in todo}
            for fut in as_completed(futures):
                i, v = futures[fut]
                try:
                    row = fut.result()
                except Exception as exc:  # noqa: BLE001 -- a worker lost is a failed run, not a failed sweep
                    row = {"id": i, **{f"vary.{k}": x for k, x in v.items()}, "status": "error",
                           "error": f"{type(exc).__name__}: {exc}"}
                write_atomic(runs_dir / f"{i}.json", json.dumps(row, default=float).encode())
                done += 1
                if progress is not None:
                    progress(done / len(variations))
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    rows = [json.loads((runs_dir / f"{i}.json").read_text()) for i in ids]
    summary = write_summary(rows, out)
    return {"runs": len(rows), "ran": len(todo), "skipped": len(rows) - len(todo),
            "failed": sum(r["status"] != "ok" for r in rows), "summary": summary}


def write_summary(rows: list[dict], out: Path) -> Path:
    """Write the rows as ``summary.parquet`` and ``summary.csv`` in ``out``; returns the Parquet path."""
    import pyarrow as pa

    from . import tables
    from .io import write_atomic

    names = list(dict.fromkeys(k for r in rows for k in r))  # rows of failed runs have fewer columns
    table = pa.table({k: pa.array([r.get(k) for r in rows]) for k in names})
    write_atomic(out / "summary.parquet", tables.to_parquet(table))
    write_atomic(out / "summary.csv", tables.to_csv(table).encode())
    return out / "summary.parquet"


FAULT_KINDS = ("dead_cell_rate", "stuck_wheel_rate", "free_wheel_rate", "dead_link_rate", "stuck_sensor_rate")


def fault_study(scenario: str, kind: str, rates, samples: int, out_dir: str | Path, *, duration: float | None = None,
                scheduler: str | None = None, workers: int | None = None,
                progress: Callable[[float], None] | None = None) -> list[dict]:
    """Monte-Carlo study of a sorting scenario against a failure rate: for each rate in ``rates`` (probability per
    item of fault ``kind``, one of :data:`FAULT_KINDS`), ``samples`` runs with fault seeds 0..samples-1, as a sweep
    in ``out_dir`` (resumable; see :func:`run_sweep`). Returns one row per rate: ``rate``, ``runs``, ``failed``,
    ``delivered_fraction`` (parcels at their right exit / parcels due by the end of the run, ``t_start`` <= duration;
    mean and std over the seeds),
    ``delivery_time_mean_s``, ``collisions``, ``misrouted``, ``lost`` (means), also written to ``study.json``."""
    from .io import write_atomic
    from .scenario import load_scenario

    if kind not in FAULT_KINDS:
        raise ScenarioError("kind", f"{kind!r} is not a fault rate; use one of {', '.join(FAULT_KINDS)}")
    rates = [float(r) for r in rates]
    if not rates or any(not 0.0 <= r <= 1.0 for r in rates):
        raise ScenarioError("rates", "give one or more failure rates in [0, 1]")
    if int(samples) < 1:
        raise ScenarioError("samples", f"must be at least 1, got {samples}")
    sc, text = load_scenario(scenario)
    if sc.control is None or sc.control.program != "sort":
        raise ScenarioError("control.program", "a fault study needs a sorting scenario (program = \"sort\"): it "
                            "counts parcels delivered to the right exit")
    base = tomllib.loads(text)
    if duration is not None:
        if not duration > 0:
            raise ScenarioError("duration", f"must be positive (s), got {duration}")
        base["duration"] = float(duration)
    spec = SweepSpec(base=scenario, vary={f"faults.{kind}": rates, "faults.seed": list(range(int(samples)))})
    res = run_sweep(spec, base, out_dir, scheduler=scheduler, workers=workers, progress=progress)
    import pyarrow.parquet as pq

    table = pq.read_table(res["summary"]).to_pylist()
    end = base["duration"]
    due = sum(p.t_start <= end for p in sc.parcels)  # parcels put on by the end; later ones cannot count
    rows = []
    for rate in rates:
        sel = [r for r in table if r[f"vary.faults.{kind}"] == rate]
        ok = [r for r in sel if r["status"] == "ok"]
        frac = np.array([r["sorting.correct"] / due for r in ok])

        def mean(col):
            vals = [r[col] for r in ok if r.get(col) is not None]
            return float(np.mean(vals)) if vals else None

        rows.append({"rate": rate, "runs": len(sel), "failed": len(sel) - len(ok), "parcels_due": due,
                     "delivered_fraction": float(frac.mean()) if len(frac) else None,
                     "delivered_fraction_std": float(frac.std()) if len(frac) else None,
                     "delivery_time_mean_s": mean("sorting.delivery_time_mean_s"),
                     "collisions": mean("sorting.collisions"), "misrouted": mean("sorting.misrouted"),
                     "lost": mean("sorting.lost")})
    write_atomic(Path(out_dir) / "study.json", json.dumps({"scenario": sc.name, "fault": kind, "samples": samples,
                                                           "parcels_due": due, "rows": rows}, indent=2).encode())
    return rows
