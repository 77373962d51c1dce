"""Results out: trajectories and events as CSV, a JSON summary, the scenario as run.

Files are written atomically (to a temporary name in the same folder, then renamed), so an interrupted run never
leaves a half-written file under a final name.

Columns:
- ``trajectories.csv``: parcel, t (s), x, y (m), theta (rad), vx, vy (m/s), omega (rad/s), one row per sample.
- ``events.csv``: parcel, t (s), kind (support | tip | contact | release), entered, left, lifted, touched (cell
  ids separated by spaces), partner (the other parcel of a contact), the state at the event (as above), message.
- ``network.csv`` (networked runs): per control tick, t (s), sentences sent / received, bytes sent / received,
  lost, corrupted, undetected, dropped, unaddressed, latency_mean and latency_max (s; empty when nothing arrived).
- ``cell_traffic.csv`` (networked runs): per cell, cell id, x, y (m), sentences and bytes sent and received.
- ``sensors.csv`` (networked runs with ``[sensors] record = true``): per tick and cell, t (s), cell, the readings
  s0.. (0/1), the wheels' mean surface speeds over the tick wheel0, wheel1 and their commands command0, command1
  (m/s).
"""

from __future__ import annotations

import csv
import io as _io
import json
import os
import tempfile
from pathlib import Path

from .dynamics import Event
from .parcel import STATE_FIELDS
from .sim import RunResult


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


def trajectories_csv(result: RunResult) -> str:
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(("parcel", "t", *STATE_FIELDS))
    for pr in result.parcels:
        tr = pr.trajectory
        for t, y in zip(tr.times, tr.states):
            w.writerow((pr.spec.name, repr(float(t)), *(repr(float(v)) for v in y)))
    return buf.getvalue()


def _ids(ids) -> str:
    return " ".join(str(i) for i in ids)


def events_csv(result: RunResult) -> str:
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(("parcel", "t", "kind", "entered", "left", "lifted", "touched", "partner", *STATE_FIELDS,
                "message"))
    for pr in result.parcels:
        e: Event
        for e in pr.trajectory.events:
            w.writerow((pr.spec.name, repr(e.t), e.kind, _ids(e.entered), _ids(e.left), _ids(e.lifted),
                        _ids(e.touched), e.partner, *(repr(v) for v in e.state), e.message))
    return buf.getvalue()


NETWORK_COLUMNS = ("t", "sent", "received", "bytes_sent", "bytes_received", "lost", "corrupted", "undetected",
                   "dropped", "unaddressed", "latency_mean", "latency_max")


def network_csv(result: RunResult) -> str:
    rec = result.network
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(NETWORK_COLUMNS)
    for k in range(len(rec.per_tick["t"])):
        row = []
        for c in NETWORK_COLUMNS:
            v = rec.per_tick[c][k]
            row.append("" if isinstance(v, float) and v != v else repr(v.item()))
        w.writerow(row)
    return buf.getvalue()


def cell_traffic_csv(result: RunResult) -> str:
    rec = result.network
    pos = result.setup.cells.positions
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(("cell", "x", "y", "sent", "received", "bytes_sent", "bytes_received"))
    for i in range(len(pos)):
        w.writerow((i, repr(float(pos[i, 0])), repr(float(pos[i, 1])), *(int(rec.per_cell[f"cell_{k}"][i]) for k in
                    ("sent", "received", "bytes_sent", "bytes_received"))))
    return buf.getvalue()


def sensors_csv(result: RunResult) -> str:
    buf = _io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    S = result.setup.sensors.count
    w.writerow(("t", "cell", *(f"s{k}" for k in range(S)), "wheel0", "wheel1", "command0", "command1"))
    for t, readings, wheels, command in result.sensor_log:
        for cell in range(len(readings)):
            w.writerow((repr(float(t)), cell, *(int(b) for b in readings[cell]),
                        *(repr(float(v)) for v in (*wheels[cell], *command[cell]))))
    return buf.getvalue()


def write_results(result: RunResult, out_dir: str | Path, scenario_text: str | None = None) -> dict[str, Path]:
    """Write trajectories.csv, events.csv, summary.json and scenario.toml (when its text is given) into
    ``out_dir``. Returns the paths written, by kind."""
    out = Path(out_dir)
    paths = {
        "trajectories": out / "trajectories.csv",
        "events": out / "events.csv",
        "summary": out / "summary.json",
    }
    write_atomic(paths["trajectories"], trajectories_csv(result))
    write_atomic(paths["events"], events_csv(result))
    write_atomic(paths["summary"], json.dumps(result.summary(), indent=2) + "\n")
    if result.network is not None:
        paths["network"] = out / "network.csv"
        paths["cell_traffic"] = out / "cell_traffic.csv"
        write_atomic(paths["network"], network_csv(result))
        write_atomic(paths["cell_traffic"], cell_traffic_csv(result))
    if result.sensor_log is not None:
        paths["sensors"] = out / "sensors.csv"
        write_atomic(paths["sensors"], sensors_csv(result))
    if scenario_text is not None:
        paths["scenario"] = out / "scenario.toml"
        write_atomic(paths["scenario"], scenario_text)
    return paths
