"""Sentences: the short messages cells send to their neighbours (paper Section 3: "short sentences which are made up
of labeled pieces of data, or words, punctuated by a checksum").

Byte format (all multi-byte fields big-endian)::

    offset  size  field
    0       1     start byte 0x7E
    1       1     payload length L in bytes (0 .. MAX_PAYLOAD)
    2       L     words, back to back; each word is
                    label (1 byte, 0..255) | type (1 byte) | value (size set by the type)
    2+L     2     CRC-16/CCITT (polynomial 0x1021, initial value 0xFFFF) over bytes 1 .. 2+L-1

Word types: ``U8`` (1 byte), ``BOOL`` (1 byte, 0 or 1), ``I16`` (2), ``U16`` (2), ``I32`` (4), ``F32`` (4, IEEE 754,
finite). A label appears at most once per sentence.

Decoding checks, in order: length of the buffer, start byte, declared length against the maximum and against the
buffer (truncated / trailing bytes), checksum, then the words (known type, value inside the payload, valid BOOL,
finite F32, no repeated label). Any failure raises :class:`SentenceError` whose ``reason`` says which check failed;
nothing is ever returned from a sentence that failed a check.

What the checksum catches: CRC-16/CCITT detects every error of an odd number of bits, every 2-bit error and every
burst of up to 16 bits in a sentence of this size; other random corruptions pass the CRC with probability 2^-16
(about 1.5e-5), and the structural checks reject some of those. ``tests/test_sentence.py`` measures the rate.
"""

from __future__ import annotations

import binascii
import enum
import math
import numbers
import struct
from dataclasses import dataclass

START = 0x7E
MAX_PAYLOAD = 60
"""Largest payload in bytes: a sentence is at most 64 bytes on the wire."""
OVERHEAD = 4
"""Bytes around the payload: start, length and the two checksum bytes."""


class WordType(enum.IntEnum):
    """The type of a word's value and its size on the wire."""

    U8 = 1
    BOOL = 2
    I16 = 3
    U16 = 4
    I32 = 5
    F32 = 6


_FORMAT = {WordType.U8: ">B", WordType.BOOL: ">B", WordType.I16: ">h", WordType.U16: ">H", WordType.I32: ">i",
           WordType.F32: ">f"}
SIZE = {t: struct.calcsize(f) for t, f in _FORMAT.items()}
"""Value size in bytes of each word type."""


class SentenceError(ValueError):
    """A sentence could not be encoded or was rejected when decoded; ``reason`` is a short keyword."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        super().__init__(f"{reason}: {detail}" if detail else reason)


@dataclass(frozen=True)
class Word:
    """A labelled value. ``label`` is 0..255; ``value`` must fit ``type``."""

    label: int
    type: WordType
    value: int | float | bool


def checksum(data: bytes) -> int:
    """CRC-16/CCITT (0x1021, initial 0xFFFF) of ``data``."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode(words: list[Word] | tuple[Word, ...]) -> bytes:
    """The sentence carrying ``words``. Raises SentenceError for a value that does not fit its type, a repeated
    label, or a payload longer than MAX_PAYLOAD.

    >>> s = encode([Word(1, WordType.U8, 3), Word(2, WordType.I16, -20)])
    >>> decode(s) == [Word(1, WordType.U8, 3), Word(2, WordType.I16, -20)]
    True
    """
    payload = bytearray()
    seen = set()
    for w in words:
        if isinstance(w.label, bool) or not isinstance(w.label, numbers.Integral) or not 0 <= w.label <= 255:
            raise SentenceError("bad label", f"labels are 0..255, got {w.label!r}")
        label = int(w.label)
        if label in seen:
            raise SentenceError("repeated label", f"label {label} appears twice")
        seen.add(label)
        try:
            t = WordType(w.type)
        except ValueError:
            raise SentenceError("unknown word type", repr(w.type)) from None
        payload += bytes((label, int(t))) + _pack(t, w.value)
    if len(payload) > MAX_PAYLOAD:
        raise SentenceError("oversized", f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes((len(payload),)) + bytes(payload)
    return bytes((START,)) + body + checksum(body).to_bytes(2, "big")


def _pack(t: WordType, value) -> bytes:
    if t is WordType.F32:
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise SentenceError("bad value", f"F32 needs a finite number, got {value!r}")
        if abs(value) > 3.4028234663852886e38:
            raise SentenceError("bad value", f"{value!r} overflows F32")
        return struct.pack(">f", float(value))
    if t is WordType.BOOL:
        if value not in (0, 1, True, False):
            raise SentenceError("bad value", f"BOOL needs 0 or 1, got {value!r}")
        return bytes((int(value),))
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        if isinstance(value, numbers.Real) and float(value).is_integer():
            value = int(value)
        else:
            raise SentenceError("bad value", f"{t.name} needs an integer, got {value!r}")
    value = int(value)
    try:
        return struct.pack(_FORMAT[t], value)
    except struct.error:
        raise SentenceError("bad value", f"{value!r} does not fit {t.name}") from None


def decode(data: bytes) -> list[Word]:
    """The words of sentence ``data``. Raises SentenceError (with ``reason``) for anything malformed."""
    data = bytes(data)
    if len(data) < OVERHEAD:
        raise SentenceError("truncated", f"{len(data)} bytes is shorter than an empty sentence")
    if data[0] != START:
        raise SentenceError("bad start byte", f"0x{data[0]:02x}")
    n = data[1]
    if n > MAX_PAYLOAD:
        raise SentenceError("oversized", f"declared payload of {n} bytes exceeds {MAX_PAYLOAD}")
    if len(data) < n + OVERHEAD:
        raise SentenceError("truncated", f"declared {n} payload bytes, got {len(data) - OVERHEAD}")
    if len(data) > n + OVERHEAD:
        raise SentenceError("trailing bytes", f"{len(data) - n - OVERHEAD} bytes after the checksum")
    body = data[1:2 + n]
    if checksum(body) != int.from_bytes(data[2 + n:4 + n], "big"):
        raise SentenceError("checksum mismatch")
    words = []
    seen = set()
    i = 2
    end = 2 + n
    while i < end:
        if end - i < 2:
            raise SentenceError("word overruns payload", f"a word header at byte {i} is cut off")
        label, code = data[i], data[i + 1]
        try:
            t = WordType(code)
        except ValueError:
            raise SentenceError("unknown word type", f"type code {code} at byte {i + 1}") from None
        size = SIZE[t]
        if i + 2 + size > end:
            raise SentenceError("word overruns payload", f"{t.name} value at byte {i + 2} is cut off")
        (value,) = struct.unpack(_FORMAT[t], data[i + 2:i + 2 + size])
        if t is WordType.BOOL:
            if value > 1:
                raise SentenceError("bad value", f"BOOL byte {value}")
            value = bool(value)
        elif t is WordType.F32 and not math.isfinite(value):
            raise SentenceError("bad value", "non-finite F32")
        if label in seen:
            raise SentenceError("repeated label", f"label {label}")
        seen.add(label)
        words.append(Word(label, t, value))
        i += 2 + size
    return words


def wire_size(types) -> int:
    """Bytes on the wire of a sentence with words of the given types."""
    return OVERHEAD + sum(2 + SIZE[WordType(t)] for t in types)
