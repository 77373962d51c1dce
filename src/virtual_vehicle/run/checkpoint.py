"""Checkpoints as data: a small tree codec (JSON plus numbered numpy arrays) and the checkpoint file around it.

Reading a checkpoint never runs code named by the file: there is no pickle anywhere; the document is read with
:func:`json.loads` and every array with ``numpy.lib.format.read_array(..., allow_pickle=False)``; the only objects
made are plain values (None, bool, int, float, str, bytes, lists, tuples, dicts, sets, deques, numpy arrays and
scalars of numeric or boolean dtypes), numpy random generators of the standard bit generators (from their
``bit_generator.state`` dict), and instances of the classes the caller allowlists, made with ``cls.__new__`` and
given their recorded fields (no ``__init__``, no ``__setstate__``). A node naming anything else is an error.

File layout (format version :data:`FORMAT_VERSION`): the header line ``virtual_vehicle checkpoint 2`` and then a zip
archive holding ``checkpoint.json`` (the document: format version, package version, the run's kind, its scenario
and the encoded run state) and ``arrays/<k>.npy`` for every array the state refers to.

Tree encoding (the JSON form of a value): None, bool, str, int and finite floats stand for themselves (JSON floats
round-trip exactly); every other value is an object with a ``"$"`` tag: ``float`` (non-finite), ``np`` (a numpy
scalar: dtype and value), ``array`` (index ``k`` among the arrays), ``rows`` (a list of equal-shaped arrays stored as
one stacked array), ``list``, ``tuple``, ``dict`` (items as [key, value] pairs, so any key), ``set``, ``frozenset``,
``deque``, ``bytes`` (base64), ``rng``, ``obj`` (an allowlisted class by name, with its fields), ``ext`` (an object
the reader supplies by name: parts of the immutable setup rebuilt from the scenario) and ``ref`` (the same object as
an earlier node with that ``@`` number: shared arrays, lists, dicts and objects stay shared).
"""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import math
import zipfile
from collections import deque

import numpy as np

FORMAT_VERSION = 2
"""The checkpoint format this version writes and reads (1 was a pickle, which is not read: it could run code)."""

MAGIC = b"virtual_vehicle checkpoint "
HEADER = MAGIC + str(FORMAT_VERSION).encode() + b"\n"

_BIT_GENERATORS = {cls.__name__: cls for cls in (np.random.PCG64, np.random.PCG64DXSM, np.random.MT19937,
                                                  np.random.Philox, np.random.SFC64)}


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read (bad header, archive, document or tree)."""


def _nonfinite(v: float):
    return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")


def _float(text: str) -> float:
    if text not in ("nan", "inf", "-inf"):
        raise CheckpointError(f"bad float {text!r}")
    return float(text)


class Encoder:
    """Encodes trees of values into JSON-ready form, collecting their arrays (:attr:`arrays`).

    ``classes``: allowlisted classes by name (dataclasses are written by their fields, others by ``__slots__`` or
    ``__dict__``); ``externals``: objects not written but named, for the reader to supply."""

    def __init__(self, classes: dict[str, type], externals: dict[str, object] | None = None):
        self.names = {cls: name for name, cls in classes.items()}
        self.external = {id(obj): name for name, obj in (externals or {}).items() if obj is not None}
        self._externals = externals  # (kept alive, so their ids stay theirs)
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
        if a.dtype.hasobject:
            raise TypeError("arrays of Python objects are not data")
        self.arrays.append(a)
        return len(self.arrays) - 1

    def encode(self, x, where: str = "state"):
        """The JSON-ready form of ``x`` (its arrays appended to :attr:`arrays`). Raises TypeError, naming ``where``
        in the tree, for a value that is not data nor an allowlisted class."""
        if id(x) in self.external:
            return {"$": "ext", "name": self.external[id(x)]}
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
            if (len(x) > 1 and all(type(e) is np.ndarray and id(e) not in self._memo and id(e) not in self.external
                                   for e in x)
                    and len({(e.shape, e.dtype.str) for e in x}) == 1 and not x[0].dtype.hasobject):
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
        if t is np.random.Generator:
            bg = x.bit_generator
            if type(bg).__name__ not in _BIT_GENERATORS:
                raise TypeError(f"{where}: bit generator {type(bg).__name__} is not written")
            n = self._tag(x)
            return {"$": "rng", "@": n, "bit_generator": type(bg).__name__, "state": self.encode(bg.state, where)}
        if t in self.names:
            n = self._tag(x)
            if dataclasses.is_dataclass(x):
                fields = {f.name: getattr(x, f.name) for f in dataclasses.fields(x)}
            elif hasattr(t, "__slots__"):
                fields = {k: getattr(x, k) for k in t.__slots__ if hasattr(x, k)}
            else:
                fields = dict(vars(x))
            return {"$": "obj", "@": n, "class": self.names[t],
                    "fields": [[k, self.encode(v, f"{where}.{k}")] for k, v in fields.items()]}
        raise TypeError(f"{where}: a {t.__module__}.{t.__qualname__} is not written into a checkpoint")


class Decoder:
    """The inverse of :class:`Encoder`: makes only the values and allowlisted classes listed in the module notes.
    Raises CheckpointError for any node it does not know."""

    def __init__(self, arrays: list[np.ndarray], classes: dict[str, type], externals: dict[str, object] | None = None):
        self.arrays = arrays
        self.classes = classes
        self.externals = externals or {}
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
        if tag == "ext":
            name = node.get("name")
            if type(name) is not str or name not in self.externals:
                raise CheckpointError(f"unknown external {name!r}")
            return self.externals[name]
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
        if tag == "rng":
            cls = _BIT_GENERATORS.get(node.get("bit_generator"))
            if cls is None:
                raise CheckpointError(f"unknown bit generator {node.get('bit_generator')!r}")
            bg = cls()
            bg.state = self.decode(node.get("state"))
            return self._register(node, np.random.Generator(bg))
        if tag == "obj":
            name = node.get("class")
            cls = self.classes.get(name) if type(name) is str else None
            if cls is None:
                raise CheckpointError(f"class {name!r} is not one a checkpoint may hold")
            obj = self._register(node, cls.__new__(cls))
            allowed = ({f.name for f in dataclasses.fields(cls)} if dataclasses.is_dataclass(cls)
                       else set(cls.__slots__) if hasattr(cls, "__slots__") else None)
            for pair in self._items(node, "fields"):
                if type(pair) is not list or len(pair) != 2 or type(pair[0]) is not str:
                    raise CheckpointError("fields must be [name, value] pairs")
                if allowed is not None and pair[0] not in allowed:
                    raise CheckpointError(f"{name} has no field {pair[0]!r}")
                if allowed is None and (pair[0].startswith("__") or pair[0] in vars(cls)):
                    raise CheckpointError(f"{name}.{pair[0]} is not a field")
                object.__setattr__(obj, pair[0], self.decode(pair[1]))
            return obj
        raise CheckpointError(f"unknown node {tag!r}")


def encode(tree, classes: dict[str, type], externals: dict[str, object] | None = None):
    """``(document, arrays)``: the JSON-ready form of ``tree`` and the arrays it refers to."""
    enc = Encoder(classes, externals)
    return enc.encode(tree), enc.arrays


def decode(document, arrays: list[np.ndarray], classes: dict[str, type], externals: dict[str, object] | None = None):
    """The tree :func:`encode` encoded (see :class:`Decoder`)."""
    return Decoder(arrays, classes, externals).decode(document)


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
        old = " (format 1 was a Python pickle, which is never loaded: it could run code)" if version == "1" else ""
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
