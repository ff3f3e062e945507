"""Envelope serialization: round trips (hypothesis), golden bytes, every decode error."""

from __future__ import annotations

import json

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundstation.bus.envelope import (
    ALLOWED_DTYPES,
    HEADER_STRUCT,
    Envelope,
    Header,
    decode,
    encode,
    from_bytes,
    pack_frames,
    pack_header,
    to_bytes,
    unpack_frames,
    unpack_header,
)
from groundstation.bus.errors import EnvelopeError, SchemaError
from groundstation.bus.topics import TOPICS
from groundstation.errors import GroundstationError

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20)
)
json_values = st.recursive(
    json_scalars,
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4)
    ),
    max_leaves=12,
)
dtypes = st.sampled_from(sorted(ALLOWED_DTYPES)).map(np.dtype)


@st.composite
def any_array(draw):
    dtype = draw(dtypes)
    if draw(st.booleans()):
        dtype = dtype.newbyteorder(">")  # big-endian input is converted to little-endian
    a = draw(hnp.arrays(dtype, hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5)))
    how = draw(st.sampled_from(["as_is", "transpose", "stride"]))
    if how == "transpose":
        a = a.T  # Fortran order: made C-contiguous on encode
    elif how == "stride" and a.ndim >= 1:
        a = a[::2]
    return a


headers = st.builds(
    Header,
    type=st.text(min_size=1, max_size=40).filter(lambda s: 0 < len(s.encode()) <= 255),
    schema=st.integers(0, 2**16 - 1),
    seq=st.integers(0, 2**64 - 1),
    source_ns=st.integers(-(2**63), 2**63 - 1),
    recv_ns=st.integers(-(2**63), 2**63 - 1),
    origin=st.integers(0, 2**32 - 1),
)
envelopes = st.builds(
    Envelope,
    topic=st.text(min_size=1, max_size=30),
    header=headers,
    payload=st.dictionaries(st.text(max_size=10), json_values, max_size=5),
    arrays=st.dictionaries(st.text(min_size=1, max_size=10), any_array(), max_size=4),
)


def _same(a: Envelope, b: Envelope) -> None:
    assert a.topic == b.topic and a.header == b.header and a.payload == b.payload
    assert list(a.arrays) == list(b.arrays)
    for k, x in a.arrays.items():
        x = np.asarray(x)
        y = b.arrays[k]
        assert y.shape == x.shape
        want = x.dtype.newbyteorder("<") if x.dtype.byteorder == ">" else x.dtype
        assert y.dtype == want
        assert y.tobytes() == x.astype(y.dtype).tobytes()


@settings(max_examples=150, deadline=None)
@given(envelopes)
def test_frames_round_trip_and_reencode_byte_for_byte(env):
    frames = encode(env)
    back = decode(frames)
    _same(env, back)
    assert [bytes(f) for f in encode(back)] == [bytes(f) for f in frames]


@settings(max_examples=100, deadline=None)
@given(envelopes)
def test_blob_round_trip(env):
    blob = to_bytes(env)
    _same(env, from_bytes(blob))
    assert to_bytes(from_bytes(blob)) == blob
    assert pack_frames(unpack_frames(blob)) == blob


def test_arrays_decode_zero_copy_read_only():
    a = np.arange(12, dtype="<f4").reshape(3, 4)
    frames = [bytes(f) for f in encode(Envelope("t", Header("x", 1, 0, 0), {}, {"a": a}))]
    out = decode(frames).arrays["a"]
    assert not out.flags.writeable and out.base is not None
    np.testing.assert_array_equal(out, a)


def test_zero_d_and_empty_arrays_keep_shape():
    arrays = {"s": np.float64(2.5), "e": np.zeros((0, 3), np.int32), "b": np.array([True, False])}
    back = decode(encode(Envelope("t", Header("x", 1, 0, 0), {}, arrays)))
    assert back.arrays["s"].shape == () and back.arrays["s"] == 2.5
    assert back.arrays["e"].shape == (0, 3) and back.arrays["e"].dtype == np.int32
    assert back.arrays["b"].tolist() == [True, False]


def test_golden_header_bytes():
    h = Header("imu_sample", schema=2, seq=5, source_ns=123, recv_ns=-1, origin=7)
    assert pack_header(h).hex() == (
        "475342" "01" "0200" "0a" "00" "07000000" "0500000000000000"
        "7b00000000000000" "ffffffffffffffff" + b"imu_sample".hex()
    )  # fmt: skip
    assert unpack_header(pack_header(h)) == h
    assert HEADER_STRUCT.size == 36


def test_errors_derive_from_the_root():
    assert issubclass(EnvelopeError, GroundstationError)
    assert issubclass(SchemaError, EnvelopeError)


def _good_frames() -> list[bytes]:
    env = Envelope(
        "samples.imu",
        Header("imu_sample", 1, 0, 10),
        {},
        {"accel_mps2": np.zeros(3), "gyro_radps": np.ones(3)},
    )
    return [bytes(f) for f in encode(env)]


def _meta(frames, meta):
    return [frames[0], frames[1], json.dumps(meta).encode(), *frames[3:]]


def _arrs(frames, descs):
    return _meta(frames, {"a": descs, "p": {}})


def _hdr(frames, **kw):
    h = unpack_header(frames[1])
    fields = {**h.__dict__, **kw}
    return [frames[0], pack_header(Header(**fields)), *frames[2:]]


DESC = [["accel_mps2", "<f8", [3]], ["gyro_radps", "<f8", [3]]]
CASES = {
    "too few frames": (lambda f: f[:2], "frame count mismatch"),
    "missing buffer": (lambda f: f[:-1], "frame count mismatch"),
    "extra buffer": (lambda f: [*f, b"x"], "frame count mismatch"),
    "bad magic": (lambda f: [f[0], b"XYZ" + f[1][3:], *f[2:]], "bad magic"),
    "format version": (lambda f: [f[0], f[1][:3] + b"\x09" + f[1][4:], *f[2:]], "format version"),
    "short header": (lambda f: [f[0], f[1][:20], *f[2:]], "header frame too short"),
    "type length": (lambda f: [f[0], f[1] + b"z", *f[2:]], "header frame is"),
    "type not utf8": (
        lambda f: [f[0], f[1][:6] + b"\x01" + f[1][7:36] + b"\xff", *f[2:]],
        "not valid UTF-8",
    ),
    "topic not utf8": (lambda f: [b"\xff\xfe", *f[1:]], "topic frame"),
    "meta not json": (lambda f: [f[0], f[1], b"{not json", *f[3:]], "not valid JSON"),
    "meta not object": (lambda f: _meta(f, [1, 2]), "exactly the keys"),
    "meta extra key": (lambda f: _meta(f, {"a": DESC, "p": {}, "z": 1}), "exactly the keys"),
    "payload not dict": (lambda f: _meta(f, {"a": DESC, "p": [1]}), "payload must be"),
    "descs not list": (lambda f: _meta(f, {"a": {}, "p": {}}), "must be a JSON list"),
    "bad descriptor": (lambda f: _arrs(f, [["x", "<f8"], DESC[1]]), "descriptor"),
    "negative dim": (lambda f: _arrs(f, [["x", "<f8", [-3]], DESC[1]]), "descr"),
    "object dtype": (lambda f: _arrs(f, [["x", "|O", [3]], DESC[1]]), "not allowed"),
    "big endian dtype": (lambda f: _arrs(f, [["x", ">f8", [3]], DESC[1]]), "dtype"),
    "duplicate names": (lambda f: _arrs(f, [DESC[0], DESC[0]]), "duplicate"),
    "size mismatch": (lambda f: _arrs(f, [["accel_mps2", "<f8", [4]], DESC[1]]), "needs"),
    "short buffer": (lambda f: [*f[:3], f[3][:-1], f[4]], "buffer holds"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_every_decode_error_is_named(case):
    mutate, words = CASES[case]
    with pytest.raises(EnvelopeError, match=words):
        decode(mutate(_good_frames()), TOPICS)


TABLE_CASES = {
    "unknown topic": (lambda f: [b"nope", *f[1:]], "unknown topic"),
    "wrong type": (lambda f: _hdr(f, type="pose_sample"), "unknown type/schema"),
    "wrong schema": (lambda f: _hdr(f, schema=9), "unknown type/schema"),
    "missing array": (lambda f: _meta(f[:4], {"a": DESC[:1], "p": {}}), "missing"),
    "unknown field": (lambda f: _meta(f, {"a": DESC, "p": {"x": 1}}), "unknown"),
    "wrong shape": (lambda f: _arrs(f, [DESC[0], ["gyro_radps", "<f4", [6]]]), "dtype"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(TABLE_CASES))
def test_table_checks_on_decode(case):
    mutate, words = TABLE_CASES[case]
    frames = mutate(_good_frames())
    decode(frames)  # structurally fine without the table
    with pytest.raises(SchemaError, match=words):
        decode(frames, TOPICS)


@pytest.mark.parametrize(
    ("payload", "arrays", "words"),
    [
        ({"x": float("nan")}, {}, "not JSON-serializable"),
        ({"x": object()}, {}, "not JSON-serializable"),
        ({}, {"o": np.array([object()])}, "not allowed"),
        ({}, {"s": np.array(["abc"])}, "not allowed"),
        ({}, {"r": np.zeros(2, dtype=[("a", "<f8")])}, "not allowed"),
    ],
)
def test_encode_errors(payload, arrays, words):
    with pytest.raises(EnvelopeError, match=words):
        encode(Envelope("t", Header("x", 1, 0, 0), payload, arrays))


@pytest.mark.parametrize(
    "header",
    [
        Header("x", 1, -1, 0),
        Header("x", 70000, 0, 0),
        Header("", 1, 0, 0),
        Header("x" * 256, 1, 0, 0),
    ],
)
def test_header_out_of_range(header):
    with pytest.raises(EnvelopeError):
        pack_header(header)


@pytest.mark.parametrize(
    ("cut", "words"),
    [
        (lambda b: b[:2], "too short"),
        (lambda b: b[:8], "length of frame"),
        (lambda b: b[:-1], "truncated in frame"),
        (lambda b: b + b"\x00", "trailing"),
        (lambda b: b"\xff\xff\xff\xff" + b[4:], "corrupt"),
    ],
)
def test_blob_errors(cut, words):
    blob = pack_frames(_good_frames())
    with pytest.raises(EnvelopeError, match=words):
        from_bytes(cut(blob))
