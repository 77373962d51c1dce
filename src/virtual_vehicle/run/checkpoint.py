"""Checkpoints as data: a small tree codec (JSON plus numbered numpy arrays) and the checkpoint file around it.

A checkpoint holds a run's state, never its model: the state is declared by the run as a tree of plain data (the
``to_data`` forms of the objects that hold it, :mod:`virtual_vehicle.model.state_data`), and the setup is built
again from the scenario the checkpoint holds. Reading one never runs code named by the file: there is no pickle
anywhere; the document is read with :func:`json.loads` and every array with
``numpy.lib.format.read_array(..., allow_pickle=False)``; the only objects made are plain values (None, bool, int,
float, str, bytes, lists, tuples, dicts, sets, deques, numpy arrays of numeric, boolean or text dtypes and numpy
scalars of numeric or boolean dtypes). A node naming anything else is an error; the objects of the run are made by
the run's own code from that data, which checks it.

File layout (format version :data:`FORMAT_VERSION`): the header line ``virtual_vehicle checkpoint 4`` and then a zip
archive holding ``checkpoint.json`` (the document: format version, package version, the run's kind, its scenario
and the encoded run state) and ``arrays/<k>.npy`` for every array the state refers to.

Tree encoding (the JSON form of a value): None, bool, str, int and finite floats stand for themselves (JSON floats
round-trip exactly); every other value is an object with a ``"$"`` tag: ``float`` (non-finite), ``np`` (a numpy
scalar: dtype and value), ``array`` (index ``k`` among the arrays), ``rows`` (a list of equal-shaped arrays stored as
one stacked array), ``list``, ``tuple``, ``dict`` (items as [key, value] pairs, so any key), ``set``, ``frozenset``,
``deque``, ``bytes`` (base64) and ``ref`` (the same object as an earlier node with that ``@`` number: shared arrays,
lists and dicts of a cell program's state stay shared).
"""

from __future__ import annotations

import base64
import io
import json
import math
import zipfile
from collections import deque

import numpy as np

FORMAT_VERSION = 4
"""The checkpoint format this version writes and reads (1 was a pickle, which is not read: it could run code; 2 held
objects of allowlisted classes by their fields, not the state's data forms; 3 kept no riding parcel's proof)."""

_OLD_FORMATS = {"1": "format 1 was a Python pickle, which is never loaded: it could run code",
                "2": "format 2 held the run's objects, not its state as data",
                "3": "format 3 kept no riding parcel's proof, on which the windows a run rides depend"}

MAGIC = b"virtual_vehicle checkpoint "
HEADER = MAGIC + str(FORMAT_VERSION).encode() + b"\n"


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read (bad header, archive, document or tree)."""


def _nonfinite(v: float):
    return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")


def _float(text: str) -> float:
    if text not in ("nan", "inf", "-inf"):
        raise CheckpointError(f"bad float {text!r}")
    return float(text)


class Encoder:
    """Encodes trees of plain values into JSON-ready form, collecting their arrays (:attr:`arrays`)."""

    def __init__(self):
        self.arrays: list[np.ndarray] = []
        self._memo: dict[int, int] = {}
        self._alive: list = []  # everything memoized stays alive while encoding, so no id is reused

    def _tag(self, x) -> int | None:
        """The object's ``@`` number when first seen (None when seen before)."""
        if id(x) in self._memo:
            return None
        self._memo[id(x)] = n = len(self._memo)
        self._alive.append(x)
        return n

    def _array(self, a: np.ndarray) -> int:
        if a.dtype.kind not in "biufU":
            raise TypeError(f"arrays of dtype {a.dtype} are not data")
        self.arrays.append(a)
        return len(self.arrays) - 1

    def encode(self, x, where: str = "state"):
        """The JSON-ready form of ``x`` (its arrays appended to :attr:`arrays`). Raises TypeError, naming ``where``
        in the tree, for a value that is not plain data."""
        t = type(x)
        if x is None or t is bool or t is str or t is int:
            return x
        if t is float:
            return x if math.isfinite(x) else {"$": "float", "v": _nonfinite(x)}
        if isinstance(x, np.generic):
            if x.dtype.kind not in "biuf" or (x.dtype.kind == "f" and x.dtype.itemsize > 8):
                raise TypeError(f"{where}: numpy scalar of dtype {x.dtype} is not written")
            v = x.item()
            if isinstance(v, float) and not math.isfinite(v):
                v = _nonfinite(v)
            return {"$": "np", "dtype": x.dtype.str, "v": v}
        if id(x) in self._memo:
            return {"$": "ref", "@": self._memo[id(x)]}
        if t is np.ndarray:
            return {"$": "array", "@": self._tag(x), "k": self._array(x), "ro": not x.flags.writeable}
        if t is list:
            if (len(x) > 1 and all(type(e) is np.ndarray and id(e) not in self._memo for e in x)
                    and len({(e.shape, e.dtype.str) for e in x}) == 1 and x[0].dtype.kind in "biufU"):
                return {"$": "rows", "@": self._tag(x), "k": self._array(np.stack(x))}
            n = self._tag(x)
            return {"$": "list", "@": n, "items": [self.encode(e, f"{where}[{k}]") for k, e in enumerate(x)]}
        if t is tuple:
            return {"$": "tuple", "items": [self.encode(e, f"{where}[{k}]") for k, e in enumerate(x)]}
        if t is dict:
            n = self._tag(x)
            return {"$": "dict", "@": n, "items": [[self.encode(k, f"{where} key"), self.encode(v, f"{where}[{k!r}]")]
                                                   for k, v in x.items()]}
        if t in (set, frozenset):
            n = self._tag(x)
            return {"$": t.__name__, "@": n, "items": [self.encode(e, where) for e in x]}
        if t is deque:
            n = self._tag(x)
            return {"$": "deque", "@": n, "maxlen": x.maxlen,
                    "items": [self.encode(e, f"{where}[{k}]") for k, e in enumerate(x)]}
        if t is bytes:
            return {"$": "bytes", "v": base64.b64encode(x).decode("ascii")}
        raise TypeError(f"{where}: a {t.__module__}.{t.__qualname__} is not written into a checkpoint")


class Decoder:
    """The inverse of :class:`Encoder`: makes only the plain values listed in the module notes. Raises
    CheckpointError for any node it does not know."""

    def __init__(self, arrays: list[np.ndarray]):
        self.arrays = arrays
        self._memo: dict[int, object] = {}

    def _register(self, node: dict, obj):
        n = node.get("@")
        if n is not None:
            if type(n) is not int or n in self._memo:
                raise CheckpointError(f"bad object number {n!r}")
            self._memo[n] = obj
        return obj

    def _array(self, k) -> np.ndarray:
        if type(k) is not int or not 0 <= k < len(self.arrays):
            raise CheckpointError(f"no array {k!r}")
        return self.arrays[k]

    def _items(self, node, key: str = "items") -> list:
        items = node.get(key)
        if type(items) is not list:
            raise CheckpointError(f"{key} must be a list")
        return items

    def decode(self, node):
        """The value a node of :meth:`Encoder.encode` stands for."""
        t = type(node)
        if node is None or t in (bool, str, int, float):
            return node
        if t is list:
            raise CheckpointError("an untagged list")
        if t is not dict:
            raise CheckpointError(f"unexpected {t.__name__}")
        tag = node.get("$")
        if tag == "float":
            return _float(node.get("v"))
        if tag == "np":
            dtype = np.dtype(str(node.get("dtype")))
            if dtype.kind not in "biuf":
                raise CheckpointError(f"numpy scalar of dtype {dtype}")
            v = node.get("v")
            if type(v) is str:
                v = _float(v)
            if type(v) not in (bool, int, float):
                raise CheckpointError("bad numpy scalar")
            return np.array(v, dtype=dtype)[()]
        if tag == "ref":
            n = node.get("@")
            if type(n) is not int or n not in self._memo:
                raise CheckpointError(f"reference to unknown object {n!r}")
            return self._memo[n]
        if tag == "array":
            a = self._array(node.get("k"))
            if node.get("ro"):
                a.setflags(write=False)
            return self._register(node, a)
        if tag == "rows":
            a = self._array(node.get("k"))
            if a.ndim < 1 or len(a) > MAX_ROWS:
                raise CheckpointError(f"rows of an array of shape {a.shape}")
            return self._register(node, list(a))
        if tag == "list":
            out = self._register(node, [])
            out.extend(self.decode(e) for e in self._items(node))
            return out
        if tag == "tuple":
            return tuple(self.decode(e) for e in self._items(node))
        if tag == "dict":
            out = self._register(node, {})
            for pair in self._items(node):
                if type(pair) is not list or len(pair) != 2:
                    raise CheckpointError("dict items must be [key, value] pairs")
                out[self.decode(pair[0])] = self.decode(pair[1])
            return out
        if tag == "set":
            out = self._register(node, set())
            out.update(self.decode(e) for e in self._items(node))
            return out
        if tag == "frozenset":
            return self._register(node, frozenset(self.decode(e) for e in self._items(node)))
        if tag == "deque":
            maxlen = node.get("maxlen")
            if maxlen is not None and type(maxlen) is not int:
                raise CheckpointError("bad deque length")
            out = self._register(node, deque(maxlen=maxlen))
            out.extend(self.decode(e) for e in self._items(node))
            return out
        if tag == "bytes":
            v = node.get("v")
            if type(v) is not str:
                raise CheckpointError("bad bytes")
            return base64.b64decode(v.encode("ascii"), validate=True)
        raise CheckpointError(f"unknown node {tag!r}")


def encode(tree):
    """``(document, arrays)``: the JSON-ready form of ``tree`` (plain data) and the arrays it refers to."""
    enc = Encoder()
    return enc.encode(tree), enc.arrays


def decode(document, arrays: list[np.ndarray]):
    """The tree :func:`encode` encoded (see :class:`Decoder`)."""
    return Decoder(arrays).decode(document)


def pack(document: dict, arrays: list[np.ndarray]) -> bytes:
    """A checkpoint file's bytes: the header, then a zip of ``checkpoint.json`` and the arrays as ``.npy``."""
    buf = io.BytesIO()
    buf.write(HEADER)
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        z.writestr("checkpoint.json", json.dumps({**document, "arrays": len(arrays)}, allow_nan=False))
        for k, a in enumerate(arrays):
            with z.open(f"arrays/{k}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)
    return buf.getvalue()


MAX_BYTES = 8 * 2**30
"""The most a checkpoint may hold unpacked (B): a file that claims more is refused before anything is allocated."""
MAX_ROWS = 10**7
"""The most arrays one stacked list of a checkpoint may hold."""


def _read_array(z: zipfile.ZipFile, name: str) -> np.ndarray:
    """One ``.npy`` member, refused unless its header's shape and type account for exactly its size."""
    info = z.getinfo(name)
    with z.open(info) as f:
        version = np.lib.format.read_magic(f)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in read_header:
            raise CheckpointError(f"{name}: npy version {version}")
        shape, _, dtype = read_header[version](f)
        if dtype.hasobject:
            raise CheckpointError(f"{name}: an array of Python objects")
        if dtype.kind not in "biufU":
            raise CheckpointError(f"{name}: an array of dtype {dtype}")
        if info.file_size - f.tell() != math.prod(shape) * dtype.itemsize:
            raise CheckpointError(f"{name}: its header's shape {shape} does not fit its {info.file_size} bytes")
        f.seek(0)
        return np.lib.format.read_array(f, allow_pickle=False)


def unpack(data: bytes) -> tuple[dict, list[np.ndarray]]:
    """The document and arrays of a checkpoint file's bytes. Raises CheckpointError, saying why, for anything else
    (another format version included)."""
    if not data.startswith(MAGIC):
        raise CheckpointError("not a virtual_vehicle checkpoint")
    line, _, rest = data.partition(b"\n")
    version = line[len(MAGIC):].decode("ascii", "replace")
    if version != str(FORMAT_VERSION):
        old = f" ({_OLD_FORMATS[version]})" if version in _OLD_FORMATS else ""
        raise CheckpointError(f"checkpoint format {version!r}{old}; this version reads format {FORMAT_VERSION} "
                              "only: run the scenario again")
    try:
        with zipfile.ZipFile(io.BytesIO(rest)) as z:
            size = sum(info.file_size for info in z.infolist())
            if size > MAX_BYTES:
                raise CheckpointError(f"it would unpack to {size} bytes, more than the {MAX_BYTES} a checkpoint may")
            document = json.loads(z.read("checkpoint.json").decode("utf-8"))
            if type(document) is not dict or type(document.get("arrays")) is not int:
                raise CheckpointError("the document is not a checkpoint's")
            arrays = []
            for k in range(document["arrays"]):
                arrays.append(_read_array(z, f"arrays/{k}.npy"))
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, KeyError, ValueError, OSError, EOFError,
            UnicodeDecodeError, RecursionError, MemoryError) as exc:
        raise CheckpointError(f"damaged ({type(exc).__name__}: {exc})") from None
    if document.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint format {document.get('format_version')!r}; this version reads format "
                              f"{FORMAT_VERSION} only")
    return document, arrays
