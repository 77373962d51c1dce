"""Sentences: round trip for every word type, every corruption rejected with a reason (single-bit and short bursts
always; random corruption missed at a measured rate), and a fuzz test of the decoder."""

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virtual_vehicle.cells.network.sentence import (
    MAX_PAYLOAD,
    SentenceError,
    Word,
    WordType,
    checksum,
    decode,
    encode,
    wire_size,
)

VALUES = {
    WordType.U8: st.integers(0, 255),
    WordType.BOOL: st.booleans(),
    WordType.I16: st.integers(-(2**15), 2**15 - 1),
    WordType.U16: st.integers(0, 2**16 - 1),
    WordType.I32: st.integers(-(2**31), 2**31 - 1),
    WordType.F32: st.floats(width=32, allow_nan=False, allow_infinity=False),
}


@st.composite
def sentences(draw, max_words=8):
    n = draw(st.integers(0, max_words))
    labels = draw(st.lists(st.integers(0, 255), min_size=n, max_size=n, unique=True))
    words = []
    size = 0
    for lab in labels:
        t = draw(st.sampled_from(list(WordType)))
        if size + 2 + struct.calcsize(">" + {"U8": "B", "BOOL": "B", "I16": "h", "U16": "H", "I32": "i", "F32": "f"}[t.name]) > MAX_PAYLOAD:
            break
        words.append(Word(lab, t, draw(VALUES[t])))
        size = wire_size([w.type for w in words]) - 4
    return words


def test_checksum_is_crc16_ccitt_false():
    assert checksum(b"123456789") == 0x29B1  # the standard check value of CRC-16/CCITT-FALSE


@settings(max_examples=300)
@given(sentences())
def test_round_trip_every_type(words):
    data = encode(words)
    assert len(data) == wire_size([w.type for w in words])
    out = decode(data)
    assert [(w.label, w.type) for w in out] == [(w.label, w.type) for w in words]
    for a, b in zip(out, words):
        if a.type is WordType.F32:
            assert a.value == struct.unpack(">f", struct.pack(">f", b.value))[0]
        else:
            assert a.value == b.value


@settings(max_examples=200)
@given(sentences(), st.data())
def test_every_single_bit_error_is_caught(words, data):
    s = bytearray(encode(words))
    bit = data.draw(st.integers(0, 8 * len(s) - 1))
    s[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(SentenceError):
        decode(bytes(s))


@settings(max_examples=200)
@given(sentences(), st.data())
def test_every_burst_up_to_16_bits_is_caught(words, data):
    s = bytearray(encode(words))
    nbits = 8 * len(s)
    length = data.draw(st.integers(1, min(16, nbits)))
    start = data.draw(st.integers(0, nbits - length))
    pattern = data.draw(st.integers(0, 2 ** length - 1)) | 1 | (1 << (length - 1))  # first and last bits flip
    for k in range(length):
        if pattern >> k & 1:
            b = start + k
            s[b // 8] ^= 1 << (b % 8)
    with pytest.raises(SentenceError):
        decode(bytes(s))


def test_truncated_oversized_and_trailing_are_rejected_with_reasons():
    s = encode([Word(1, WordType.I32, 123456), Word(2, WordType.F32, 1.5)])
    for cut in range(len(s)):
        with pytest.raises(SentenceError, match="truncated|checksum|overruns|oversized"):
            decode(s[:cut])
    with pytest.raises(SentenceError, match="trailing"):
        decode(s + b"\x00")
    with pytest.raises(SentenceError, match="bad start"):
        decode(b"\x00" + s[1:])
    too_long = bytes((0x7E, MAX_PAYLOAD + 1)) + bytes(MAX_PAYLOAD + 3)
    with pytest.raises(SentenceError, match="oversized"):
        decode(too_long)
    with pytest.raises(SentenceError, match="oversized"):
        encode([Word(i, WordType.I32, 0) for i in range(11)])


def test_encoder_rejects_values_that_do_not_fit():
    for w in (Word(1, WordType.U8, 256), Word(1, WordType.I16, 40000), Word(1, WordType.F32, math.inf),
              Word(1, WordType.BOOL, 2), Word(1, WordType.U8, 1.5), Word(300, WordType.U8, 1),
              Word(1, WordType.F32, 1e39)):
        with pytest.raises(SentenceError):
            encode([w])
    with pytest.raises(SentenceError, match="repeated"):
        encode([Word(1, WordType.U8, 1), Word(1, WordType.U8, 2)])


def _reframe(body: bytes) -> bytes:
    """Wrap a crafted payload in a correct header and checksum (to reach the word checks)."""
    b = bytes((len(body),)) + body
    return bytes((0x7E,)) + b + checksum(b).to_bytes(2, "big")


def test_structurally_bad_words_are_rejected_even_with_a_good_checksum():
    cases = {
        "unknown word type": bytes((1, 99, 0)),
        "word overruns payload": bytes((1, int(WordType.I32), 0, 0)),
        "repeated label": bytes((1, int(WordType.U8), 5, 1, int(WordType.U8), 6)),
        "bad value": bytes((1, int(WordType.BOOL), 7)),
    }
    for reason, body in cases.items():
        with pytest.raises(SentenceError, match=reason):
            decode(_reframe(body))
    with pytest.raises(SentenceError, match="bad value"):
        decode(_reframe(bytes((1, int(WordType.F32))) + struct.pack(">f", math.nan)))
    with pytest.raises(SentenceError, match="overruns"):
        decode(_reframe(bytes((1,))))


def test_random_corruption_miss_rate_is_within_the_crc_bound():
    """Replace 2..8 random bytes of random sentences: the fraction decoded without error (a miss) must be consistent
    with at most 2^-16. 200 000 trials: expected <= ~3 misses; we allow 12 (a Poisson tail of 1e-4)."""
    rng = np.random.default_rng(7)
    misses = 0
    trials = 200_000
    for _ in range(trials):
        n = int(rng.integers(1, 6))
        words = [Word(lab, WordType.I16, int(v)) for lab, v in zip(rng.choice(256, n, replace=False),
                                                                    rng.integers(-30000, 30000, n))]
        s = bytearray(encode(words))
        k = int(rng.integers(2, min(8, len(s)) + 1))
        pos = rng.choice(len(s), k, replace=False)
        for p in pos:
            s[p] = (s[p] + int(rng.integers(1, 256))) % 256
        try:
            decode(bytes(s))
            misses += 1
        except SentenceError:
            pass
    assert misses <= 12, f"{misses} undetected corruptions in {trials}"


@settings(max_examples=2000)
@given(st.binary(max_size=80))
def test_decoder_fuzz_never_misbehaves(data):
    """Arbitrary bytes: either a list of well-typed words or SentenceError, nothing else."""
    try:
        words = decode(data)
    except SentenceError as exc:
        assert exc.reason
        return
    assert encode(words) == data  # anything accepted is exactly a valid sentence


@settings(max_examples=200)
@given(st.integers(0, 255), st.booleans(), st.integers(-(2**15), 2**15 - 1),
       st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_schema_fast_encoder_matches_the_reference_encoder(u8, flag, i16, f32):
    from virtual_vehicle.cells.network.messages import Schema

    schema = Schema.of(a=(10, WordType.U8), b=(11, WordType.BOOL), c=(12, WordType.I16), d=(13, WordType.F32))
    values = {"a": np.uint8(u8), "b": np.bool_(flag), "c": np.int16(i16), "d": np.float32(f32)}
    reference = encode([Word(10, WordType.U8, u8), Word(11, WordType.BOOL, flag), Word(12, WordType.I16, i16),
                        Word(13, WordType.F32, float(np.float32(f32)))])
    assert schema.to_bytes(values) == reference
    assert schema.from_bytes(reference) == {"a": u8, "b": flag, "c": i16, "d": float(np.float32(f32))}
    with pytest.raises(SentenceError):
        schema.to_bytes({**values, "a": 300})
    with pytest.raises(SentenceError):
        schema.to_bytes({**values, "d": float("inf")})
