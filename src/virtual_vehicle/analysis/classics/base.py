"""What every classic result returns and writes: a :class:`Result` with the source's statement beside our numbers,
a figure (PNG) and a table (CSV with a units row in the Arrow metadata, as the run folder writes them).

Units: SI (m, s, rad, N, N m) unless a column's name says otherwise (``_deg`` columns are degrees).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from virtual_vehicle.run.files import write_atomic
from virtual_vehicle.run.tables import to_csv


@dataclass
class Result:
    """One classic result, reproduced.

    Attributes:
        name: the registry name (``virtual-vehicle reproduce NAME``).
        title: one line saying what was reproduced.
        source: the reference (authors, title, venue, year, section or equation).
        statement: what the source says, quoted where we hold its text, else marked as a paraphrase.
        ours: our measurement in one line, to stand beside ``statement``.
        passed: whether our measurement agrees with the statement within the tolerance ``tolerance`` names.
        tolerance: the tolerance or the property checked, in words.
        numbers: the measured quantities by name (SI units, or as the name says).
        files: the figure and table written.
    """

    name: str
    title: str
    source: str
    statement: str
    ours: str
    passed: bool
    tolerance: str
    numbers: dict = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)


def write_table(path: Path, columns: dict[str, tuple[list | np.ndarray, str]]) -> Path:
    """Write name -> (values, unit) as CSV at ``path`` (floats round-trip exactly); returns the path. Strings stay
    strings, numbers become float64 (integers int64), so that a reader gets the same types as from a run folder."""
    fields, arrays = [], []
    for name, (values, unit) in columns.items():
        values = list(values)
        if values and all(isinstance(v, str) for v in values):
            typ = pa.string()
        elif values and all(isinstance(v, (bool, np.bool_)) for v in values):
            typ = pa.bool_()
        elif values and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in values):
            typ = pa.int64()
        else:
            typ = pa.float64()
            values = [None if v is None else float(v) for v in values]
        fields.append(pa.field(name, typ, metadata={"unit": unit}))
        arrays.append(pa.array(values, type=typ))
    write_atomic(path, to_csv(pa.Table.from_arrays(arrays, schema=pa.schema(fields))))
    return path


def new_figure(nrows: int, ncols: int, width: float, height: float):
    """A matplotlib figure off screen (Agg), with its axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(nrows, ncols, figsize=(width, height), squeeze=False)


def save_figure(fig, path: Path) -> Path:
    """Write the figure as PNG at ``path`` (atomically) and close it."""
    import io

    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    write_atomic(path, buf.getvalue())
    return path
