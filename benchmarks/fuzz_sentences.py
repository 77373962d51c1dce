"""Fuzz the sentence decoder with a million inputs (issue: reliability). Prints figures; exits 1 on a violation.

Inputs, in equal shares: random byte strings (0-80 bytes); valid sentences with random bit flips; valid sentences
with replaced, inserted or deleted bytes or truncated/extended. For each input the decoder must either return words
that re-encode to exactly the input, or raise SentenceError; anything else is a violation. A mutated sentence that
decodes is an undetected corruption: counted and compared with the CRC's 2^-16 bound.

Run: ``python benchmarks/fuzz_sentences.py [N]`` (default 1 000 000; about a minute).
"""

from __future__ import annotations

import collections
import sys
import time

import numpy as np

from virtual_vehicle.cells.network.sentence import SentenceError, Word, WordType, decode, encode

TYPES = list(WordType)
RANGES = {WordType.U8: (0, 256), WordType.BOOL: (0, 2), WordType.I16: (-(2**15), 2**15), WordType.U16: (0, 2**16),
          WordType.I32: (-(2**31), 2**31), WordType.F32: None}


def random_sentence(rng) -> bytes:
    n = int(rng.integers(0, 7))
    words = []
    for label in rng.choice(256, n, replace=False):
        t = TYPES[int(rng.integers(len(TYPES)))]
        if t is WordType.F32:
            value = float(np.float32(rng.normal() * 10.0 ** int(rng.integers(-3, 6))))
        else:
            lo, hi = RANGES[t]
            value = int(rng.integers(lo, hi))
        words.append(Word(int(label), t, value))
    return encode(words)


def mutate(rng, s: bytes) -> bytes:
    b = bytearray(s)
    kind = int(rng.integers(4))
    if kind == 0:  # bit flips
        for bit in rng.choice(8 * len(b), int(rng.integers(1, 9)), replace=True):
            b[bit // 8] ^= 1 << (bit % 8)
    elif kind == 1:  # replaced bytes
        for pos in rng.choice(len(b), int(rng.integers(1, 4)), replace=True):
            b[pos] = int(rng.integers(256))
    elif kind == 2:  # inserted or deleted byte
        pos = int(rng.integers(len(b) + 1))
        if rng.random() < 0.5 and len(b):
            del b[min(pos, len(b) - 1)]
        else:
            b.insert(pos, int(rng.integers(256)))
    else:  # truncated or extended
        b = b[:int(rng.integers(len(b)))] if rng.random() < 0.5 else b + bytes(rng.integers(0, 256, int(rng.integers(1, 4))).tolist())
    return bytes(b)


def main(n: int = 1_000_000, seed: int = 0) -> int:
    rng = np.random.default_rng(seed)
    reasons = collections.Counter()
    accepted = undetected = mutated_total = violations = 0
    start = time.perf_counter()
    for k in range(n):
        share = k % 3
        original = None
        if share == 0:
            data = bytes(rng.integers(0, 256, int(rng.integers(0, 81))).tolist())
        else:
            original = random_sentence(rng)
            data = mutate(rng, original)
            mutated_total += data != original
        try:
            words = decode(data)
        except SentenceError as exc:
            reasons[exc.reason] += 1
            continue
        except Exception as exc:  # noqa: BLE001 - any other exception is what we hunt for
            violations += 1
            print(f"VIOLATION: {type(exc).__name__}: {exc} for {data.hex()}")
            continue
        accepted += 1
        if encode(words) != data:
            violations += 1
            print(f"VIOLATION: accepted bytes do not re-encode: {data.hex()}")
        if original is not None and data != original:
            undetected += 1
    wall = time.perf_counter() - start
    print(f"# Sentence decoder fuzz: {n} inputs in {wall:.1f} s ({n / wall:,.0f} per s), seed {seed}")
    print(f"accepted {accepted}; rejected {n - accepted - violations}; violations {violations}")
    print("rejections by reason: " + ", ".join(f"{r} {c}" for r, c in reasons.most_common()))
    print(f"undetected corruptions: {undetected} of {mutated_total} mutated sentences "
          f"({undetected / max(mutated_total, 1):.2e}; CRC-16 bound 2^-16 = {2**-16:.2e})")
    return 1 if violations else 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000))
