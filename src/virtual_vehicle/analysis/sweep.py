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

Before anything runs, every variation about to run is applied to the base and checked as its run would check it
(parsed and built): a path that leads nowhere or a value the scenario rejects raises :class:`ScenarioError` naming
the ``vary`` path, and nothing runs.

Every variation runs in its own task; a finished run is written at once (atomically) to ``runs/<id>.json`` in the
output folder (``id`` a hash of the variation and of the base scenario's content, so a resumed sweep redoes only what
is missing and an edited sweep, or one of another base, never reuses a result that is not its own). A run that
fails is recorded with its error (``status = "error"``) and the rest go on. A run lost to the cluster (a worker
died, its future was cancelled, the scattered base was lost) is not a result: it is submitted again, the base
scattered again when the cluster lost it, up to :data:`MAX_ATTEMPTS` attempts in all; a run lost that often is
recorded with ``status = "lost"`` and is retried whenever the sweep is run again. ``retry_failed`` also redoes the
runs recorded as ``"error"``. The base scenario is scattered to the workers under a key of its own (a hash of its
content plus a random suffix), so sweeps sharing one cluster never see each other's data.
At the end every row is collected into ``summary.parquet`` (and ``summary.csv``): the varied values as columns
``vary.<path>``, ``status`` (``"ok"`` / ``"error"`` / ``"lost"``), ``error``, ``attempts`` (tries this row took),
and the run summary's scalars flattened to dotted
names (``sorting.correct``, ``network.sentences_sent``, ...; units as in ``summary.json``: SI), with
``parcels.tipped`` and, for runs of at most 10 parcels, each parcel's as ``parcel.<name>.<key>``
(``parcel.box.end.x``, ``parcel.box.path_length_m``, ...).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import logging
import signal
import threading
import time
import tomllib
import traceback
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from virtual_vehicle.errors import ScenarioError, VirtualVehicleError
from virtual_vehicle.run.interrupt import Interrupts, without_sigint

Scalar = Union[bool, int, float, str]
PER_PARCEL_COLUMNS = 10
"""Runs with at most this many parcels also get each parcel's summary scalars as ``parcel.<name>.<key>``."""
MAX_ATTEMPTS = 3
"""Times a run lost to the cluster (worker death, cancelled future, lost data) is tried before it is recorded as
``"lost"``."""
SCATTER_TIMEOUT_S = 60.0
"""Seconds the cluster has to take the base scenario (it waits for a worker, e.g. one restarting after a crash)."""
CONNECT_TIMEOUT_S = 5.0
"""Seconds to wait for a ``scheduler`` given by address to answer before giving up with :class:`SweepError`."""


class SweepError(VirtualVehicleError):
    """The sweep could not run (e.g. no Dask scheduler answered at the address given)."""


class SweepInterrupted(KeyboardInterrupt):
    """A sweep stopped by Ctrl-C (KeyboardInterrupt) after its cluster was shut down: ``kept`` of its ``runs`` rows
    are in ``out/runs`` (each complete); running the sweep again on ``out`` resumes."""

    def __init__(self, kept: int, runs: int, out: Path):
        self.kept, self.runs, self.out = kept, runs, out
        super().__init__(f"sweep interrupted: {kept} of {runs} runs kept in {out / 'runs'}")


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


class _Points(SweepSpec):
    """A grid sweep of the given ``points`` only (each a variation of the grid ``vary`` spans), as the fault study
    runs one draw of several seeds that draw the same faults. Each point's run id is its grid id, so a study folder
    made before keeps its runs."""

    points: list[dict[str, Scalar]]

    def variations(self) -> list[dict[str, Scalar]]:
        return [dict(p) for p in self.points]


def load_sweep(path: str | Path) -> tuple[SweepSpec, dict]:
    """Read and validate a sweep file; returns the spec and the base scenario's raw tables. Raises ScenarioError."""
    from virtual_vehicle.config.scenario import load_scenario

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


def base_digest(base: dict) -> str:
    """A content hash of the raw scenario tables ``base`` (16 hex digits of a SHA-256 of their JSON)."""
    return hashlib.sha256(json.dumps(base, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_id(variation: dict, base: dict | None = None) -> str:
    """A short stable id of a variation (12 hex digits of a SHA-256 of its JSON and, given the ``base`` it applies
    to, of the base's :func:`base_digest`)."""
    key = variation if base is None else {"base": base_digest(base), "vary": variation}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]


def sweep_ids(spec: SweepSpec, variations: list[dict], base: dict) -> list[str]:
    """The run id of each variation: a random sweep's draws are samples even when two draw the same values, so each
    is its own run; a grid's combinations are distinct by construction."""
    if spec.mode == "random":
        return [run_id({"sample": k, **v}, base) for k, v in enumerate(variations)]
    return [run_id(v, base) for v in variations]


def _matches(path: str, loc: str) -> bool:
    """Whether a ``vary`` path and a validation error's field (``parcels[0].mu``) name the same place, or one lies
    inside the other (``*`` stands for any list index)."""
    p = path.split(".")
    q = loc.replace("[", ".").replace("]", "").split(".")
    return all(a == b or (a == "*" and b.isdigit()) for a, b in zip(p, q))


def check_variations(base: dict, variations: list[dict[str, Scalar]]) -> None:
    """Apply each variation to ``base`` and check the result as its run would (parse and build the scenario).
    Raises ScenarioError naming the ``vary`` path at fault (every path of the variation when the fault lies in their
    combination) and its value; returns None when every variation is valid."""
    from virtual_vehicle.config.scenario import parse_scenario

    for variation in variations:
        try:
            parse_scenario(apply(base, variation)).build()
        except VirtualVehicleError as exc:
            where = getattr(exc, "field", "") or ""
            paths = [p for p in variation if where and _matches(p, where)] or list(variation)
            if len(paths) == 1:
                raise ScenarioError(f"vary.{paths[0]}", f"the value {variation[paths[0]]!r} gives an invalid "
                                    f"scenario: {exc}") from None
            values = ", ".join(f"{p} = {variation[p]!r}" for p in paths)
            raise ScenarioError("vary", f"together, {values} give an invalid scenario: {exc}") from None


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
    from virtual_vehicle.config.scenario import parse_scenario
    from virtual_vehicle.run.sim import run

    row = {"id": run_id(variation, base), **{f"vary.{k}": v for k, v in variation.items()}}
    start = time.perf_counter()
    try:
        result = run(parse_scenario(apply(base, variation)).build())
        summary = result.summary()
        row.update(status="ok", error=None, **flatten(summary))
        parcels = summary["parcels"]
        row["parcels.tipped"] = sum(p["tipped_at_s"] is not None for p in parcels)
        if "sorting" in summary:  # the stalls are a list: their parcels counted by kind
            for kind in ("deadlock", "waiting"):
                row[f"sorting.stalled.{kind}"] = sum(len(s["parcels"]) for s in summary["sorting"]["stalls"]
                                                     if s["kind"] == kind)
        if len(parcels) <= PER_PARCEL_COLUMNS:
            for p in parcels:
                row.update(flatten(p, f"parcel.{p['name']}."))
    except VirtualVehicleError as exc:
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    except Exception as exc:  # noqa: BLE001 -- a sweep records any failure and goes on
        row.update(status="error", error=f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=5)}")
    row["sweep_wall_time_s"] = time.perf_counter() - start
    return row


def _lost_to_cluster(exc: BaseException) -> bool:
    """Whether a task's exception says the cluster lost the run (a worker died, the future was cancelled, its data
    or connection was lost) rather than the run itself failing."""
    from concurrent.futures import CancelledError

    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return isinstance(exc, (CancelledError, KilledWorker, CommClosedError))


def _ignore_sigint_plugin():
    """A Dask worker plugin that makes the local cluster's worker processes ignore SIGINT, those the nanny restarts
    after a crash included: Ctrl-C stops the sweep in the process that runs it, which then shuts the workers down."""
    from distributed import WorkerPlugin

    class IgnoreSigint(WorkerPlugin):
        """Ignore SIGINT in the worker's process."""

        def setup(self, worker) -> None:
            """From the worker process's main thread, where its event loop runs (a thread cannot set signals)."""
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)

    return IgnoreSigint()


def _connect(scheduler: str | None, workers: int | None):
    """A Dask client of the scheduler at address ``scheduler`` (SweepError if none answers within
    :data:`CONNECT_TIMEOUT_S`), else of a new local cluster; returns (client, cluster or None)."""
    from dask.distributed import Client, LocalCluster

    if scheduler is None:
        # Ctrl-C in a terminal reaches the whole process group: the worker processes ignore it (a disposition they
        # inherit when spawned, restarted ones too) and this process alone stops the sweep and shuts them down.
        with without_sigint():
            # dashboard_address ":0": no fixed port to collide with another cluster on this machine
            cluster = LocalCluster(n_workers=workers or 2, threads_per_worker=1, processes=True,
                                   dashboard_address=":0", silence_logs=logging.ERROR)
        try:
            client = Client(cluster)
            # on every worker, restarted ones too
            client.register_plugin(_ignore_sigint_plugin(), name="virtual-vehicle-ignore-sigint")
            return client, cluster
        except BaseException:
            cluster.close()
            raise
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT_S), None
    except (OSError, ValueError, TypeError) as exc:  # refused or timed out (OSError), a malformed address (ValueError)
        raise SweepError(f"--scheduler: no Dask scheduler answered at {scheduler!r} within {CONNECT_TIMEOUT_S:g} s "
                         f"({exc}); start one (dask scheduler) or leave --scheduler out for a local cluster") from None


def run_sweep(spec: SweepSpec, base: dict, out_dir: str | Path, *, scheduler: str | None = None,
              workers: int | None = None, progress: Callable[[float], None] | None = None,
              retry_failed: bool = False) -> dict:
    """Run every variation of ``spec`` not already in ``out_dir/runs`` on Dask (``scheduler`` the address of a
    running scheduler, which must answer within :data:`CONNECT_TIMEOUT_S`; default a local cluster of ``workers``
    processes, one thread each), writing each row as it finishes, then ``summary.parquet`` and ``summary.csv`` of all
    rows. Runs recorded as ``"lost"`` are always run again, those recorded as ``"error"`` only with
    ``retry_failed``; finished (``"ok"``) runs never. The variations about to run are checked first
    (:func:`check_variations`; ScenarioError before anything runs). Returns counts: ``runs``, ``ran``, ``skipped``
    (finished before), ``failed`` (rows not ``"ok"``), ``lost`` (of those, lost to the cluster), and ``summary`` (the
    Parquet path). Raises SweepError when the scheduler does not answer or its cluster takes no data within
    :data:`SCATTER_TIMEOUT_S` (no workers), and :class:`SweepInterrupted` (a
    KeyboardInterrupt) on Ctrl-C, after shutting the cluster down; every run finished by then is kept."""
    from dask.distributed import as_completed

    from virtual_vehicle.run.files import write_atomic

    out = Path(out_dir)
    runs_dir = out / "runs"
    variations = spec.variations()
    ids = sweep_ids(spec, variations, base)
    redo = {"lost", "error"} if retry_failed else {"lost"}
    todo = [(i, v) for i, v in zip(ids, variations) if _needs_run(runs_dir / f"{i}.json", redo)]
    check_variations(base, [v for _, v in todo])
    done = len(variations) - len(todo)
    if todo:
        client = cluster = None
        futures: dict = {}
        stop = Interrupts()
        try:
            with stop:
                client, cluster = _connect(scheduler, workers)
                runs_dir.mkdir(parents=True, exist_ok=True)
                digest = base_digest(base)

                def scatter():  # a key of this sweep's own: its base's content hash and a random suffix
                    key = f"vv-sweep-base-{digest}-{uuid.uuid4().hex[:8]}"
                    return client.scatter({key: base}, broadcast=True, timeout=SCATTER_TIMEOUT_S)[key]

                try:
                    base_future = scatter()
                except (TimeoutError, OSError) as exc:  # the scheduler has no workers
                    raise SweepError(f"the Dask cluster took no data within {SCATTER_TIMEOUT_S:g} s "
                                     f"(no workers?): {exc}") from None
                attempts = {i: 0 for i, _ in todo}

                def submit(i, v):
                    attempts[i] += 1
                    key = f"vv-run-{i}-{uuid.uuid4().hex[:8]}"
                    fut = client.submit(run_variation, base_future, v, key=key)
                    futures[fut] = (i, v)
                    return fut

                queue = as_completed([submit(i, v) for i, v in todo])
                for fut in queue:
                    stop.check()  # a Ctrl-C whose KeyboardInterrupt a finaliser swallowed stops the sweep here
                    i, v = futures.pop(fut)
                    try:
                        row = fut.result()
                    except Exception as exc:  # noqa: BLE001 -- a failed task is a row, not a failed sweep
                        lost = _lost_to_cluster(exc)
                        if lost and attempts[i] < MAX_ATTEMPTS:
                            try:
                                if base_future.status != "finished":  # the cluster lost the scattered base
                                    base_future = scatter()
                                queue.add(submit(i, v))
                                continue
                            except Exception as again:  # noqa: BLE001 -- no worker took it in time: lost
                                exc = again
                        row = {"id": i, **{f"vary.{k}": x for k, x in v.items()},
                               "status": "lost" if lost else "error", "error": f"{type(exc).__name__}: {exc}"}
                    row["id"], row["attempts"] = i, attempts[i]
                    write_atomic(runs_dir / f"{i}.json", json.dumps(row, default=float).encode())
                    done += 1
                    if progress is not None:
                        progress(done / len(variations))
        except KeyboardInterrupt:
            interrupted = True
        else:
            interrupted = stop.seen  # a signal after the last run finished: still an interrupted sweep
        finally:
            _shut_down(client, cluster, futures)
        if interrupted:
            kept = sum(not _needs_run(runs_dir / f"{i}.json", set()) for i in ids)
            raise SweepInterrupted(kept, len(ids), out)
    rows = [json.loads((runs_dir / f"{i}.json").read_text()) for i in ids]
    summary = write_summary(rows, out)
    return {"runs": len(rows), "ran": len(todo), "skipped": len(rows) - len(todo),
            "failed": sum(r["status"] != "ok" for r in rows), "lost": sum(r["status"] == "lost" for r in rows),
            "summary": summary}


def _needs_run(path: Path, redo: set[str]) -> bool:
    """Whether the run whose row would be at ``path`` is to run: no row yet, or a row whose status is in ``redo``."""
    if not path.is_file():
        return True
    try:
        return json.loads(path.read_text()).get("status") in redo
    except (OSError, ValueError):  # unreadable: run it again (rows are written atomically, so this is rare)
        return True


def _shut_down(client, cluster, futures) -> None:
    """Close the client and the local cluster ``cluster`` (its workers go with it, and what they run) or, on a cluster
    not ours, cancel this sweep's pending ``futures`` first; quietly, also after Ctrl-C."""
    import contextlib

    quiet = [logging.getLogger(n) for n in ("distributed", "tornado", "asyncio")]
    levels = [log.level for log in quiet]
    for log in quiet:
        log.setLevel(logging.CRITICAL)
    try:
        if client is not None:
            if cluster is None and futures:
                with contextlib.suppress(Exception):  # a scheduler already gone has nothing to cancel
                    client.cancel(list(futures))
            with contextlib.suppress(Exception):
                client.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()
    finally:
        for log, level in zip(quiet, levels):
            log.setLevel(level)


def write_summary(rows: list[dict], out: Path) -> Path:
    """Write the rows as ``summary.parquet`` and ``summary.csv`` in ``out``; returns the Parquet path."""
    import pyarrow as pa

    from virtual_vehicle.run import tables
    from virtual_vehicle.run.files import write_atomic

    names = list(dict.fromkeys(k for r in rows for k in r))  # rows of failed runs have fewer columns
    table = pa.table({k: pa.array([r.get(k) for r in rows]) for k in names})
    write_atomic(out / "summary.parquet", tables.to_parquet(table))
    write_atomic(out / "summary.csv", tables.to_csv(table).encode())
    return out / "summary.parquet"


FAULT_KINDS = ("dead_cell_rate", "stuck_wheel_rate", "free_wheel_rate", "dead_link_rate", "stuck_sensor_rate")


def _drawn(sc, kind: str, rate: float, seed: int):
    """The built scenario ``sc`` with its faults' ``kind`` rate and seed set to ``rate`` and ``seed``."""
    return sc.model_copy(update={"faults": sc.faults.model_copy(update={kind: rate, "seed": int(seed)})}).build()


def _draw_key(setup) -> bytes:
    """What a built scenario's fault draw is, as bytes: two draws with the same key make the same run (the fault
    seed draws nothing else)."""
    f = setup.faults
    if f is None:
        return b"none"
    return b"|".join([np.ascontiguousarray(a).tobytes() for a in (f.dead_cells, f.stuck_wheels, f.free_wheels,
                                                                     f.stuck_on, f.stuck_off)]
                     + [repr(f.dead_links).encode()])


def exits_reachable(sc, kind: str, rate: float, seed: int) -> bool:
    """Whether, in the fault draw ``seed`` at ``rate`` of fault ``kind`` (a scenario's faults with those two
    changed), every exit of the sorting scenario ``sc`` stays reachable: some live cell of each exit lane is joined to
    a live entry cell by live cells and links (the cells' graph; whether a parcel's body fits the way is the
    sorter's business). Kinds that cut nothing (wheels, sensors) leave every exit reachable."""
    return _reachable(_drawn(sc, kind, rate, seed))


def _reachable(setup) -> bool:
    """:func:`exits_reachable` of a built scenario."""
    cfg, topo, faults = setup.control.config, setup.control.topology, setup.faults
    dead = np.zeros(topo.n, bool) if faults is None else np.asarray(faults.dead_cells, bool)
    cut = set() if faults is None else {tuple(x) for x in faults.dead_links}
    live = ~dead
    seen = np.asarray(cfg["entry"], bool) & live
    frontier = list(np.flatnonzero(seen))
    while frontier:
        nxt = []
        for i in frontier:
            for q in range(topo.ports):
                j = int(topo.neighbor[i, q])
                if j < 0 or seen[j] or not live[j] or not topo.link_up[i, q]:
                    continue
                if (int(i), q) in cut or (j, int(topo.back_port[i, q])) in cut:
                    continue
                seen[j] = True
                nxt.append(j)
        frontier = nxt
    exit_id = np.asarray(cfg["exit"])
    return bool(seen.any()) and all(seen[exit_id == k].any() for k in range(int(exit_id.max()) + 1))


def fault_study(scenario: str, kind: str, rates, samples: int, out_dir: str | Path, *, duration: float | None = None,
                scheduler: str | None = None, workers: int | None = None,
                progress: Callable[[float], None] | None = None, retry_failed: bool = False) -> list[dict]:
    """Monte-Carlo study of a sorting scenario against a failure rate: for each rate in ``rates`` (probability per
    item of fault ``kind``, one of :data:`FAULT_KINDS`), ``samples`` runs with fault seeds 0..samples-1, as a sweep
    in ``out_dir`` (resumable; see :func:`run_sweep`); seeds that draw the same faults (every seed at rate 0, where
    the scenario has no other fault rate) make the same run, which is run once and counted for each of them. Returns
    one row per rate: ``rate``, ``runs`` (the draws, ``samples``), ``distinct_runs`` (those run), ``failed``,
    ``delivered_fraction`` (parcels at their right exit / parcels due by the end of the run, ``t_start`` <= duration;
    mean and std over the seeds),
    ``delivery_time_mean_s``, ``collisions``, ``misrouted``, ``lost`` (means), and the parcels due that were
    neither delivered nor lost at the end: ``on_array`` (put on the array and still there), ``waiting`` (never put
    on: their place at the entry never came free) and ``stuck`` (the two together), and of those on the array the
    ``deadlocked`` (in a deadlock the run's report names: a cycle of holds, see
    :func:`~virtual_vehicle.cells.programs.sort.stalls`), each a mean over the seeds of the runs that finished; and
    ``draws``: each kept draw's ``seed`` and ``delivered_fraction`` (lists, by seed: a mean and a standard deviation
    hide that at a high rate some draws deliver nearly all and others nothing); also written to ``study.json``.
    ``retry_failed``: see :func:`run_sweep`.

    The means are over the draws in which every exit stays reachable from an entry over live cells and links
    (:func:`exits_reachable`; a draw that cuts an exit off measures the draw, not the sorter): ``unreachable`` counts
    the draws left out, ``delivered_fraction_all`` is the mean over every finished draw."""
    from virtual_vehicle.cells.programs import program_of
    from virtual_vehicle.config.scenario import load_scenario
    from virtual_vehicle.run.files import write_atomic

    if kind not in FAULT_KINDS:
        raise ScenarioError("kind", f"{kind!r} is not a fault rate; use one of {', '.join(FAULT_KINDS)}")
    rates = [float(r) for r in rates]
    if not rates or any(not 0.0 <= r <= 1.0 for r in rates):
        raise ScenarioError("rates", "give one or more failure rates in [0, 1]")
    if len(set(rates)) != len(rates):
        raise ScenarioError("rates", f"each failure rate once, got {rates}")
    if int(samples) < 1:
        raise ScenarioError("samples", f"must be at least 1, got {samples}")
    sc, text = load_scenario(scenario)
    if sc.control is None or program_of(sc.control).SUMMARY != "sorting":  # it reads the summary's sorting block
        raise ScenarioError("control.program", "a fault study needs a sorting scenario (program = \"sort\"): it "
                            "counts parcels delivered to the right exit")
    base = tomllib.loads(text)
    if duration is not None:
        if not duration > 0:
            raise ScenarioError("duration", f"must be positive (s), got {duration}")
        base["duration"] = float(duration)
    end = base.get("duration", sc.duration)
    due = sum(p.t_start <= end for p in sc.parcels)  # parcels put on by the end; later ones cannot count
    if due == 0:
        raise ScenarioError("duration", f"no parcel is put on the array within {end:g} s: nothing to deliver")
    # the draws first: seeds that draw the same faults make the same run (at rate 0 with no other fault rate in the
    # scenario, every seed), which runs once and counts for each of them
    same, kept_of = {}, {}
    for rate in rates:
        first: dict[bytes, int] = {}
        for seed in range(int(samples)):
            setup = _drawn(sc, kind, rate, seed)
            same[rate, seed] = first.setdefault(_draw_key(setup), seed)
            if same[rate, seed] == seed:
                kept_of[rate, seed] = _reachable(setup)
    points = [{f"faults.{kind}": rate, "faults.seed": seed} for rate in rates for seed in range(int(samples))
              if same[rate, seed] == seed]
    spec = _Points(base=scenario, vary={f"faults.{kind}": rates, "faults.seed": list(range(int(samples)))},
                   points=points)
    res = run_sweep(spec, base, out_dir, scheduler=scheduler, workers=workers, progress=progress,
                    retry_failed=retry_failed)
    import pyarrow.parquet as pq

    ran = {(r[f"vary.faults.{kind}"], r["vary.faults.seed"]): r for r in pq.read_table(res["summary"]).to_pylist()}
    rows = []
    for rate in rates:  # each seed's row: its own run's, or that of the first seed that drew the same faults
        sel = [dict(ran[rate, same[rate, seed]], **{"vary.faults.seed": seed}) for seed in range(int(samples))]
        done = [r for r in sel if r["status"] == "ok"]
        kept = {seed for seed in range(int(samples)) if kept_of[rate, same[rate, seed]]}
        ok = [r for r in done if r["vary.faults.seed"] in kept]
        frac = np.array([r["sorting.correct"] / due for r in ok])

        def mean(col):
            vals = [r[col] for r in ok if r.get(col) is not None]
            return float(np.mean(vals)) if vals else None

        for r in ok:  # parcels not due by the end are "waiting" too; count only those due
            r["waiting_due"] = r["sorting.waiting"] - (len(sc.parcels) - due)
            r["stuck"] = r["sorting.on_array"] + r["waiting_due"]
            r["deadlocked"] = r.get("sorting.stalled.deadlock")
        every = [r["sorting.correct"] / due for r in done]
        by_seed = sorted((r["vary.faults.seed"], r["sorting.correct"] / due) for r in ok)
        distinct = len({same[rate, seed] for seed in range(int(samples))})
        rows.append({"rate": rate, "runs": len(sel), "distinct_runs": distinct, "failed": len(sel) - len(done),
                     "parcels_due": due,
                     "unreachable": int(samples) - len(kept),
                     "delivered_fraction_all": float(np.mean(every)) if every else None,
                     "delivered_fraction": float(frac.mean()) if len(frac) else None,
                     "delivered_fraction_std": float(frac.std()) if len(frac) else None,
                     "draws": {"seed": [s for s, _ in by_seed], "delivered_fraction": [f for _, f in by_seed]},
                     "delivery_time_mean_s": mean("sorting.delivery_time_mean_s"),
                     "collisions": mean("sorting.collisions"), "misrouted": mean("sorting.misrouted"),
                     "lost": mean("sorting.lost"), "on_array": mean("sorting.on_array"),
                     "waiting": mean("waiting_due"), "stuck": mean("stuck"), "deadlocked": mean("deadlocked")})
    write_atomic(Path(out_dir) / "study.json", json.dumps({"scenario": sc.name, "fault": kind, "samples": samples,
                                                           "parcels_due": due, "rows": rows}, indent=2).encode())
    return rows
