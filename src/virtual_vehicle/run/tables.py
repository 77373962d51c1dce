"""A run's results as column tables (Apache Arrow), for Parquet files, pandas and polars.

Every table is built here once; :mod:`virtual_vehicle.run.io` writes them as Parquet and as CSV. Each column carries
its unit in the Arrow field metadata (key ``unit``; ``""`` for counts, ids and flags), so a Parquet file says what
it holds. Units are SI. The tables and their columns:

``trajectories`` (one row per output sample and parcel)
    parcel (name), t (s), x, y (m, centre of mass), theta (rad), vx, vy (m/s), omega (rad/s).
``events`` (one row per event)
    parcel, t (s), kind (support | tip | contact | release | stick | slip), entered, left, lifted, touched (lists of
    cell ids), partner (the other parcel of a contact, or empty), the state at the event (x .. omega as above),
    message. A law with modes (stick-slip) adds its mode changes: ``stick`` where wheels catch up with the parcel,
    ``slip`` where they break away; ``message`` names them "entry:wheel" (an entry is a cell, or one wheel's contact on a layer of separate wheels).
``network`` (networked runs; one row per control tick)
    t (s), sent, received (sentences), bytes_sent, bytes_received, lost, corrupted, undetected, dropped,
    unaddressed (sentences), latency_mean, latency_max (s; null when nothing arrived).
``cell_traffic`` (networked runs; one row per cell)
    cell, x, y (m), sent, received, bytes_sent, bytes_received over the whole run.
``cells`` (networked runs with ``[sensors] record = true``; one row per tick and cell)
    t (s), cell, s0 .. s{S-1} (the presence sensors, bool), wheel0, wheel1 (the wheels' mean surface speeds over
    the tick, m/s), command0, command1 (commanded, m/s), sent, received (sentences during the tick).

>>> from virtual_vehicle.config.scenario import load_scenario
>>> from virtual_vehicle.run.sim import run
>>> tables = build(run(load_scenario("paper_2x2_inward")[0].build()))
>>> sorted(tables)
['events', 'trajectories']
>>> tables["trajectories"].schema.field("x").metadata[b"unit"]
b'm'
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from virtual_vehicle.model.parcel import STATE_FIELDS

_STATE_UNITS = dict(zip(STATE_FIELDS, ("m", "m", "rad", "m/s", "m/s", "rad/s")))
_FAULTS = ("lost", "corrupted", "undetected", "dropped", "unaddressed")
_TRAFFIC = ("sent", "received", "bytes_sent", "bytes_received")


def _table(columns: dict[str, tuple[pa.Array | list | np.ndarray, pa.DataType, str]]) -> pa.Table:
    """A table from name -> (values, Arrow type, unit)."""
    fields, arrays = [], []
    for name, (values, typ, unit) in columns.items():
        fields.append(pa.field(name, typ, metadata={"unit": unit}))
        arrays.append(pa.array(values, type=typ))
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def trajectories(result) -> pa.Table:
    """One row per output sample and parcel (see the module docstring)."""
    names, times, states = [], [], []
    for pr in result.parcels:
        tr = pr.trajectory
        names.extend([pr.spec.name] * len(tr.times))
        times.append(np.asarray(tr.times, dtype=float))
        states.append(np.asarray(tr.states, dtype=float).reshape(-1, 6))
    t = np.concatenate(times) if times else np.zeros(0)
    y = np.concatenate(states) if states else np.zeros((0, 6))
    return _table({"parcel": (names, pa.string(), ""), "t": (t, pa.float64(), "s"),
                   **{f: (y[:, k], pa.float64(), _STATE_UNITS[f]) for k, f in enumerate(STATE_FIELDS)}})


def events(result) -> pa.Table:
    """One row per event (see the module docstring)."""
    rows = [(pr.spec.name, e) for pr in result.parcels for e in pr.trajectory.events]
    ids = pa.list_(pa.int64())
    state = np.array([e.state for _, e in rows], dtype=float).reshape(-1, 6)
    return _table({
        "parcel": ([n for n, _ in rows], pa.string(), ""),
        "t": ([float(e.t) for _, e in rows], pa.float64(), "s"),
        "kind": ([e.kind for _, e in rows], pa.string(), ""),
        **{k: ([[int(i) for i in getattr(e, k)] for _, e in rows], ids, "") for k in
           ("entered", "left", "lifted", "touched")},
        "partner": ([e.partner for _, e in rows], pa.string(), ""),
        **{f: (state[:, k], pa.float64(), _STATE_UNITS[f]) for k, f in enumerate(STATE_FIELDS)},
        "message": ([e.message for _, e in rows], pa.string(), ""),
    })


def network(result) -> pa.Table:
    """One row per control tick (networked runs)."""
    tick = result.network.per_tick
    return _table({
        "t": (tick["t"], pa.float64(), "s"),
        **{k: (tick[k], pa.int64(), "") for k in (*_TRAFFIC, *_FAULTS)},
        **{k: (pa.array(tick[k], type=pa.float64(), from_pandas=True), pa.float64(), "s")
           for k in ("latency_mean", "latency_max")},  # NaN (nothing arrived) becomes null
    })


def cell_traffic(result) -> pa.Table:
    """One row per cell: where it is and what it sent and received over the run (networked runs)."""
    pos = result.setup.cells.positions
    per_cell = result.network.per_cell
    return _table({"cell": (np.arange(len(pos)), pa.int64(), ""), "x": (pos[:, 0], pa.float64(), "m"),
                   "y": (pos[:, 1], pa.float64(), "m"),
                   **{k: (per_cell[f"cell_{k}"], pa.int64(), "") for k in _TRAFFIC}})


def cells(result) -> pa.Table:
    """One row per control tick and cell: sensors, wheels and traffic (runs that recorded them)."""
    log = result.cell_log
    T, n, S = log.readings.shape
    return _table({
        "t": (np.repeat(log.t, n), pa.float64(), "s"),
        "cell": (np.tile(np.arange(n), T), pa.int64(), ""),
        **{f"s{k}": (log.readings[:, :, k].ravel(), pa.bool_(), "") for k in range(S)},
        **{f"wheel{k}": (log.wheels[:, :, k].ravel(), pa.float64(), "m/s") for k in range(2)},
        **{f"command{k}": (log.commands[:, :, k].ravel(), pa.float64(), "m/s") for k in range(2)},
        "sent": (log.sent.ravel(), pa.int64(), ""),
        "received": (log.received.ravel(), pa.int64(), ""),
    })


def build(result) -> dict[str, pa.Table]:
    """Every table the run has, by name (``network`` and ``cell_traffic`` for networked runs, ``cells`` when
    recorded)."""
    out = {"trajectories": trajectories(result), "events": events(result)}
    if result.network is not None:
        out["network"] = network(result)
        out["cell_traffic"] = cell_traffic(result)
    if result.cell_log is not None:
        out["cells"] = cells(result)
    return out


def to_csv(table: pa.Table) -> str:
    """CSV text of a table: floats written exactly (``repr``, round-trip), lists of ids space-separated, flags as 0/1,
    nulls and NaN empty."""
    import csv
    import io

    cols = []
    for field, col in zip(table.schema, table.columns):
        values = col.to_pylist()
        if pa.types.is_list(field.type):
            values = [" ".join(str(i) for i in v) for v in values]
        elif pa.types.is_floating(field.type):
            values = ["" if v is None or v != v else repr(v) for v in values]
        elif pa.types.is_boolean(field.type):
            values = ["" if v is None else int(v) for v in values]
        else:
            values = ["" if v is None else v for v in values]
        cols.append(values)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(table.column_names)
    w.writerows(zip(*cols))
    return buf.getvalue()


def to_parquet(table: pa.Table) -> bytes:
    """Parquet bytes of a table (zstd-compressed; the column units travel in the schema)."""
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()
