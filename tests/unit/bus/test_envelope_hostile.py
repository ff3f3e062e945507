"""Envelope decoding of hostile bytes: bounded, and only EnvelopeError (issue 14, point 7).

Reproducers of the three crash kinds found by fuzzing (6,186 of the 6,674 escaped exceptions):
a 5,000-digit integer in the meta JSON, deeply nested JSON, and a zero-size array with huge
dimensions. Each crashed ``decode`` with ValueError/RecursionError, and the subscriber caught only
EnvelopeError, so one such message killed the receiving process.
"""

from __future__ import annotations

import json
import random

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundstation.bus.envelope import (
    MAX_JSON_DEPTH,
    Envelope,
    Header,
    decode,
    encode,
    from_bytes,
    to_bytes,
)
from groundstation.bus.errors import EnvelopeError
from groundstation.bus.topics import TOPICS


def _good() -> list[bytes]:
    env = Envelope(
        "samples.imu",
        Header("imu_sample", 1, 3, 10, 20, 5),
        {"t_station_ns": 123},
        {"accel_mps2": np.zeros(3), "gyro_radps": np.ones(3)},
    )
    return [bytes(f) for f in encode(env)]


def _with_meta(meta: bytes) -> list[bytes]:
    f = _good()
    return [f[0], f[1], meta]


def _one_array(shape: list[int], buffer: bytes) -> list[bytes]:
    f = _good()
    return [f[0], f[1], json.dumps({"a": [["x", "<f8", shape]], "p": {}}).encode(), buffer]


def five_thousand_digit_integer() -> list[bytes]:
    f = _good()
    meta = f[2].replace(b'"t_station_ns":123', b'"t_station_ns":' + b"9" * 5000)
    assert meta != f[2]
    return [f[0], f[1], meta, *f[3:]]


def deeply_nested_json(depth: int = 100_000) -> list[bytes]:
    return _with_meta(b'{"a":[],"p":{"x":' + b"[" * depth + b"]" * depth + b"}}")


def zero_size_array_with_huge_dimensions() -> list[bytes]:
    f = _good()
    meta = {"a": [["accel_mps2", "<f8", [0, 2**70]], ["gyro_radps", "<f8", [3]]], "p": {}}
    return [f[0], f[1], json.dumps(meta).encode(), b"", f[4]]


REPRODUCERS = {
    "5000-digit integer": (five_thousand_digit_integer, "digits"),
    "deeply nested JSON": (deeply_nested_json, "nests deeper"),
    "zero-size array, huge dims": (zero_size_array_with_huge_dimensions, "digits|exceeds"),
    "float overflow to inf": (lambda: _with_meta(b'{"a":[],"p":{"x":1e999}}'), "overflows"),
    "NaN literal": (lambda: _with_meta(b'{"a":[],"p":{"x":NaN}}'), "NaN"),
    "integer beyond uint64": (
        lambda: _with_meta(b'{"a":[],"p":{"x":' + b"9" * 20 + b"}}"),
        "int64",
    ),
    "9 dimensions": (lambda: _one_array([1] * 9, b"\0" * 8), "exceeds the limits"),
    "zero-size, two dims of 2**40": (lambda: _one_array([0, 2**40, 2**40], b""), "spans more"),
    "topic frame of 10 kB": (lambda: [b"t" * 10_000, *_good()[1:]], "topic frame longer"),
}


@pytest.mark.parametrize("case", sorted(REPRODUCERS))
def test_crash_reproducers_raise_the_declared_error(case):
    build, words = REPRODUCERS[case]
    frames = build()
    with pytest.raises(EnvelopeError, match=words):
        decode(frames)
    with pytest.raises(EnvelopeError):
        decode(frames, TOPICS)


def test_nesting_at_the_limit_still_decodes():
    nested = "[" * (MAX_JSON_DEPTH - 2) + "]" * (MAX_JSON_DEPTH - 2)
    env = decode(_with_meta(f'{{"a":[],"p":{{"x":{nested}}}}}'.encode()))
    assert "x" in env.payload


def _mutate(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        op = rng.randrange(5)
        if op == 0 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 1 and b:
            b[rng.randrange(len(b))] = rng.choice((0, 0xFF, 0x7F, 0x80, rng.randrange(256)))
        elif op == 2:
            i = rng.randrange(len(b) + 1)
            b[i:i] = rng.choice((b"9" * 30, b"[[[[", b"1e999", b"-", b"\xff", b'"', b"]}"))
        elif op == 3 and b:
            i = rng.randrange(len(b))
            del b[i : i + rng.randint(1, 16)]
        else:
            b = b[: rng.randrange(len(b) + 1)]
    return bytes(b)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), which=st.integers(0, 2))
def test_mutated_frames_raise_only_envelope_error(seed, which):
    rng = random.Random(seed)
    frames = _good()
    frames[which] = _mutate(frames[which], rng)
    if rng.random() < 0.3:
        frames = frames[: rng.randint(0, len(frames))] + [b""] * rng.randint(0, 2)
    for table in (None, TOPICS):
        try:
            decode(frames, table)
        except EnvelopeError:
            pass


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_arbitrary_blobs_raise_only_envelope_error(blob):
    try:
        from_bytes(blob, TOPICS)
    except EnvelopeError:
        pass


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_mutated_blobs_raise_only_envelope_error(seed):
    rng = random.Random(seed)
    blob = to_bytes(decode(_good()))
    try:
        from_bytes(_mutate(blob, rng), TOPICS)
    except EnvelopeError:
        pass
