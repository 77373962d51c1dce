"""The data form of a run's state: numpy arrays and plain values, checked when they are read back.

A run's state is kept apart from its model (the immutable setup): every object that holds part of it writes that
part with ``to_data()`` as a dict of numpy arrays and plain scalars (None, bool, int, float, str; nested dicts and
lists of them), a list of records as a few columns, and reads it back with a ``from_data`` classmethod, or, for an
object the run makes from its setup (a delivery model, motors), with ``load_data``. Caches are never written; they
are made again as they are needed. These helpers check what is read back, so that data of the wrong keys, kinds,
dtypes or shapes raises ValueError saying where, not an error deep inside a later step.
"""

from __future__ import annotations

import numpy as np

_BIT_GENERATORS = {cls.__name__: cls for cls in (np.random.PCG64, np.random.PCG64DXSM, np.random.MT19937,
                                                  np.random.Philox, np.random.SFC64)}


def fields(d, names, where: str) -> dict:
    """``d``, checked to be a dict with exactly the keys ``names``."""
    if type(d) is not dict:
        raise ValueError(f"{where}: not a dict but a {type(d).__name__}")
    if set(d) != set(names):
        raise ValueError(f"{where}: keys {sorted(map(str, d))}, not {sorted(names)}")
    return d


def array(d: dict, key: str, kind: str, shape: tuple, where: str) -> np.ndarray:
    """``d[key]``, checked to be a numpy array of the dtype ``kind`` (``"f"`` float64, ``"i"`` int64, ``"b"`` bool,
    ``"u1"`` uint8) and of ``shape`` (a tuple whose None entries match any length)."""
    a = d[key]
    dtypes = {"f": np.dtype(np.float64), "i": np.dtype(np.int64), "b": np.dtype(bool), "u1": np.dtype(np.uint8)}
    if not isinstance(a, np.ndarray) or a.dtype != dtypes[kind]:
        got = f"{a.dtype} array" if isinstance(a, np.ndarray) else type(a).__name__
        raise ValueError(f"{where}.{key}: a {got}, not a {kind} array")
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise ValueError(f"{where}.{key}: shape {a.shape}, not {tuple('*' if s is None else s for s in shape)}")
    return a


def integer(d: dict, key: str, where: str, low: int | None = 0) -> int:
    """``d[key]``, checked to be an int (not a bool) of at least ``low`` (None: any)."""
    v = d[key]
    if type(v) is not int or (low is not None and v < low):
        raise ValueError(f"{where}.{key}: {v!r} is not an integer >= {low}")
    return v


def number(d: dict, key: str, where: str) -> float:
    """``d[key]``, checked to be a float (or an int), as a float."""
    v = d[key]
    if type(v) not in (int, float):
        raise ValueError(f"{where}.{key}: {v!r} is not a number")
    return float(v)


def text(d: dict, key: str, where: str) -> str:
    """``d[key]``, checked to be a str."""
    v = d[key]
    if type(v) is not str:
        raise ValueError(f"{where}.{key}: {v!r} is not text")
    return v


def texts(d: dict, key: str, rows: int, where: str) -> list[str]:
    """``d[key]``, checked to be a list of ``rows`` strings."""
    v = d[key]
    if type(v) is not list or len(v) != rows or not all(type(x) is str for x in v):
        raise ValueError(f"{where}.{key}: not a list of {rows} strings")
    return list(v)


def ragged(lists) -> dict:
    """Lists of ints of any lengths as two columns: ``counts`` (one per list) and ``flat`` (all of them)."""
    lists = list(lists)
    return {"counts": np.array([len(x) for x in lists], dtype=np.int64),
            "flat": np.array([v for x in lists for v in x], dtype=np.int64)}


def from_ragged(d, rows: int, where: str) -> list[tuple[int, ...]]:
    """The ``rows`` tuples of ints :func:`ragged` wrote."""
    d = fields(d, ("counts", "flat"), where)
    counts = array(d, "counts", "i", (rows,), where)
    flat = array(d, "flat", "i", (None,), where)
    if (counts < 0).any() or int(counts.sum()) != len(flat):
        raise ValueError(f"{where}: its counts do not add up to its {len(flat)} values")
    ends = np.cumsum(counts).tolist()
    values = flat.tolist()
    return [tuple(values[e - c:e]) for c, e in zip(counts.tolist(), ends)]


def rng_to_data(rng: np.random.Generator) -> dict:
    """A numpy random generator as data: its bit generator's name and state (a dict of ints, possibly arrays)."""
    bg = rng.bit_generator
    if type(bg).__name__ not in _BIT_GENERATORS:
        raise ValueError(f"bit generator {type(bg).__name__} has no data form")
    return {"bit_generator": type(bg).__name__, "state": bg.state}


def rng_from_data(d, where: str) -> np.random.Generator:
    """The generator :func:`rng_to_data` wrote, going on where it was."""
    d = fields(d, ("bit_generator", "state"), where)
    cls = _BIT_GENERATORS.get(d["bit_generator"]) if type(d["bit_generator"]) is str else None
    if cls is None:
        raise ValueError(f"{where}: unknown bit generator {d['bit_generator']!r}")
    bg = cls()
    try:
        bg.state = d["state"]
    except (TypeError, KeyError, ValueError, OverflowError) as exc:
        raise ValueError(f"{where}: not a {cls.__name__} state ({exc})") from None
    return np.random.Generator(bg)
