"""Messages of a cell program, vectorised over cells and ports.

A cell program declares a :class:`Schema`: the words its sentences carry (name, label, type). A :class:`Mailbox`
holds one sentence per (cell, port): as an outbox, what each cell sends on each port this tick; as an inbox, what
arrived on each port. Values are stored with the numpy dtype of their word type, so a program sees exactly the
values a wire would carry (an F32 is a float32) whichever delivery model runs it.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from virtual_vehicle.cells.network.sentence import (START, SentenceError, Word, WordType, checksum, decode, encode,
                                                    wire_size)
from virtual_vehicle.model import state_data

DTYPE = {WordType.U8: np.uint8, WordType.BOOL: np.bool_, WordType.I16: np.int16, WordType.U16: np.uint16,
         WordType.I32: np.int32, WordType.F32: np.float32}


def rows_any(d: np.ndarray) -> np.ndarray:
    """(m,) whether any element of each row of the boolean array ``d`` (m, ...) is set. numpy's any() along a short
    axis is slow: a row of 1, 2, 4 or 8 booleans is read as one word, a longer one column by column."""
    m = len(d)
    d = d.reshape(m, math.prod(d.shape[1:]))  # (m, -1) fails for m = 0
    k = d.shape[1]
    if k in (1, 2, 4, 8) and d.flags.c_contiguous and d.dtype == np.bool_:
        return d.view(f"u{k}")[:, 0] != 0
    out = np.zeros(m, dtype=bool)
    for q in range(k):
        out |= d[:, q]
    return out


def rows_differ(a: list, b: list, m: int) -> np.ndarray:
    """(m,) which rows differ between the arrays of ``a`` and the same arrays of ``b`` (each with first axis m)."""
    out = np.zeros(m, dtype=bool)
    for x, y in zip(a, b):
        out |= rows_any(x != y)
    return out


@dataclass(frozen=True)
class Field:
    name: str
    label: int
    type: WordType


@dataclass(frozen=True)
class Schema:
    """The words of a program's sentences. Every sentence carries all of them."""

    fields: tuple[Field, ...]

    def __post_init__(self):
        names = [f.name for f in self.fields]
        labels = [f.label for f in self.fields]
        if len(set(names)) != len(names) or len(set(labels)) != len(labels):
            raise ValueError("schema names and labels must be unique")
        wire_size([f.type for f in self.fields])  # raises for unknown types
        if self.sentence_bytes - 4 > 60:
            raise ValueError("schema does not fit one sentence")

    @classmethod
    def of(cls, **words: tuple[int, WordType]) -> "Schema":
        """``Schema.of(dist=(1, WordType.U8), speed=(2, WordType.F32))``."""
        return cls(tuple(Field(name, label, WordType(t)) for name, (label, t) in words.items()))

    @cached_property
    def sentence_bytes(self) -> int:
        """Bytes on the wire of one sentence (worked out once: every tick's traffic counts ask for it)."""
        return wire_size([f.type for f in self.fields])

    @cached_property
    def all_words(self) -> int:
        """The bit mask of every word (bit k: the schema's k-th field), as a :class:`Mailbox`'s ``words`` holds it."""
        return (1 << len(self.fields)) - 1

    def to_bytes(self, values: dict, words: int | None = None) -> bytes:
        """Encode one sentence from scalar values by name (the same bytes as :func:`sentence.encode`, through one
        precompiled struct; values that do not fit their type raise SentenceError). ``words``: a bit mask of the
        fields to carry (bit k: the k-th), the others left out of the sentence (labels say which words a sentence
        holds); None: all of them."""
        if words is not None and int(words) & self.all_words != self.all_words:
            return self._some_to_bytes(values, int(words))
        fmt, header = self._packer
        args = []
        for f, (label, code) in zip(self.fields, header):
            v = values[f.name]
            v = v.item() if hasattr(v, "item") else v
            if f.type is WordType.F32:
                if not math.isfinite(v) or abs(v) > 3.4028234663852886e38:
                    raise SentenceError("bad value", f"{f.name}={v!r} does not fit F32")
            elif f.type is WordType.BOOL:
                v = int(bool(v))
            args += (label, code, v)
        try:
            payload = struct.pack(fmt, *args)
        except struct.error as exc:
            raise SentenceError("bad value", str(exc)) from None
        body = bytes((len(payload),)) + payload
        return bytes((START,)) + body + checksum(body).to_bytes(2, "big")

    def _some_to_bytes(self, values: dict, words: int) -> bytes:
        """:meth:`to_bytes` of the fields whose bits are set in ``words`` only."""
        out = []
        for k, f in enumerate(self.fields):
            if words >> k & 1:
                v = values[f.name]
                out.append(Word(f.label, f.type, v.item() if hasattr(v, "item") else v))
        return encode(out)

    @cached_property
    def _packer(self):
        codes = {WordType.U8: "B", WordType.BOOL: "B", WordType.I16: "h", WordType.U16: "H", WordType.I32: "i",
                 WordType.F32: "f"}
        fmt = ">" + "".join("BB" + codes[f.type] for f in self.fields)
        return fmt, [(f.label, int(f.type)) for f in self.fields]

    def from_bytes(self, data: bytes, partial: bool = False) -> dict:
        """Decode one sentence to values by name; raises SentenceError (also for words not in the schema).
        ``partial``: the sentence may leave words out (only those it carries are returned)."""
        words = {w.label: w for w in decode(data)}
        out = {}
        for f in self.fields:
            w = words.get(f.label)
            if partial and w is None:
                continue
            if w is None or w.type != f.type:
                raise SentenceError("schema mismatch", f"word {f.name!r} (label {f.label}) missing or mistyped")
            out[f.name] = w.value
        if len(words) != len(out):
            raise SentenceError("schema mismatch", "unexpected words")
        return out


@dataclass
class Mailbox:
    """One sentence per (cell, port): ``present[i, p]`` says whether there is one, ``values[name][i, p]`` its words.
    ``words``: None when every sentence carries every word; else an (n, P) int64 bit mask of the words each sentence
    carries (bit k: the schema's k-th field; a program that sends only the words that changed sets it, the wire
    sends only those, and an inbox says which words arrived; the values of the others are not news)."""

    schema: Schema
    present: np.ndarray
    values: dict[str, np.ndarray]
    words: np.ndarray | None = None

    @classmethod
    def empty(cls, schema: Schema, n: int, ports: int) -> "Mailbox":
        return cls(schema, np.zeros((n, ports), dtype=bool),
                   {f.name: np.zeros((n, ports), dtype=DTYPE[f.type]) for f in schema.fields})

    @classmethod
    def broadcast(cls, schema: Schema, send: np.ndarray, ports: int, **values) -> "Mailbox":
        """Each cell with ``send[i]`` sends the same sentence on every port; values are (n,) arrays by name."""
        present = np.repeat(np.asarray(send, dtype=bool)[:, None], ports, axis=1)
        vals = {f.name: np.repeat(np.asarray(values[f.name]).astype(DTYPE[f.type])[:, None], ports, axis=1)
                for f in schema.fields}
        return cls(schema, present, vals)

    @property
    def arrays(self) -> list[np.ndarray]:
        """``present`` and every word's values, in the schema's order (and ``words`` when set): the arrays two
        mailboxes differ in."""
        return [self.present, *self.values.values(), *(() if self.words is None else (self.words,))]

    def take(self, rows: np.ndarray) -> "Mailbox":
        """The sentences of the cells ``rows`` (indices) only."""
        return Mailbox(self.schema, np.take(self.present, rows, axis=0),
                       {k: np.take(v, rows, axis=0) for k, v in self.values.items()},
                       None if self.words is None else np.take(self.words, rows, axis=0))

    def count(self) -> int:
        """Number of sentences held."""
        return int(self.present.sum())

    def to_data(self) -> dict:
        """The sentences as data: ``present`` (n, P) and ``values`` (each word's (n, P) array, by name). The schema
        is the program's (part of the setup), given again to :meth:`from_data`; ``words`` (n, P) too when set."""
        return {"present": self.present, "values": dict(self.values),
                **({} if self.words is None else {"words": self.words})}

    @classmethod
    def from_data(cls, d, schema: Schema, where: str = "mailbox") -> "Mailbox":
        """The mailbox :meth:`to_data` wrote, of sentences of ``schema``; raises ValueError for data of other keys,
        words, dtypes or shapes."""
        d = state_data.fields(d, ("present", "values", *(("words",) if isinstance(d, dict) and "words" in d else ())),
                              where)
        present = state_data.array(d, "present", "b", (None, None), where)
        words = state_data.array(d, "words", "i", present.shape, where) if "words" in d else None
        values = state_data.fields(d["values"], [f.name for f in schema.fields], f"{where}.values")
        for f in schema.fields:
            v = values[f.name]
            if not (isinstance(v, np.ndarray) and v.dtype == DTYPE[f.type] and v.shape == present.shape):
                raise ValueError(f"{where}.values[{f.name!r}]: not a {np.dtype(DTYPE[f.type])} array of shape "
                                 f"{present.shape}")
        return cls(schema, present, {f.name: values[f.name] for f in schema.fields}, words)
