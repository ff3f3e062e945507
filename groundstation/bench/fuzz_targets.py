"""The targets of ``groundstation bench fuzz``: each parser with its seeds, generators and
declared errors, and the byte-level mutator they share (see :mod:`groundstation.bench.fuzz`).

Every ``make()`` runs in the fuzzing child and returns ``(generate, run)``: ``generate(rng)``
builds one input from a seeded ``random.Random`` (pure), ``run(input)`` feeds it to the parser
the way the station does.
"""

from __future__ import annotations

import json
import math
import random
import struct
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: An input running this long is a hang: the child is killed and restarted after it, s.
HANG_S = 10.0

INTERESTING_INTS = (
    0, 1, 0x7F, 0x80, 0xFF, 0x100, 0x7FFF, 0x8000, 0xFFFF, 0x10000, 2**31 - 1, 2**31,
    2**32 - 1, 2**32, 2**48 - 1, 2**53, 2**63 - 1, 2**63, 2**64 - 1,
)  # fmt: skip
INTERESTING_FLOATS = (
    0.0, -0.0, 1e291, -1e291, 1e300, 1e308, -1e308, 3.4e38, 1e-320, math.inf, -math.inf,
    math.nan, 9.3e9, 2.0**63, 2.0**64,
)  # fmt: skip
INTERESTING_TEXT = (
    b"9" * 5000, b"[" * 2000, b"{" * 2000, b"1e999", b"-1e999", b"NaN", b"Infinity", b"-0",
    b"\xff\xfe", b"\x00", b'"', b"\\u0000", b"1e308", b"18446744073709551616",
)  # fmt: skip


# -- mutation -----------------------------------------------------------------------------------


def mutate(data: bytes, rng: random.Random, seeds: Sequence[bytes] = (), max_len: int = 1 << 16):
    """1-8 stacked byte-level mutations of ``data`` (pure function of ``rng``'s state)."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        n = len(b)
        at = rng.randrange(n + 1)
        op = rng.randrange(12)
        if op == 0 and n:
            b[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif op == 1 and n:
            b[rng.randrange(n)] = rng.choice((0, 0xFF, 0x7F, 0x80, 0xFD, 0xFE, rng.randrange(256)))
        elif op == 2:  # an interesting integer, any width, either byte order
            size = rng.choice((1, 2, 4, 8))
            v = rng.choice(INTERESTING_INTS) & ((1 << (8 * size)) - 1)
            if rng.random() < 0.3:
                v = (-v) & ((1 << (8 * size)) - 1)
            raw = v.to_bytes(size, rng.choice(("little", "big")))
            b[at : at + size] = raw
        elif op == 3:  # an interesting float or double
            x = rng.choice(INTERESTING_FLOATS)
            raw = struct.pack("<d", x) if rng.random() < 0.5 else struct.pack("<f", _f32(x))
            b[at : at + len(raw)] = raw
        elif op == 4:
            del b[at : at + rng.randint(1, 64)]
        elif op == 5 and n:  # duplicate a block
            start = rng.randrange(n)
            block = b[start : start + rng.randint(1, 256)]
            b[at:at] = block * rng.randint(1, 4)
        elif op == 6:
            b[at:at] = rng.randbytes(rng.randint(1, 32))
        elif op == 7:
            b = b[:at]
        elif op == 8 and seeds:  # splice with another seed
            other = rng.choice(seeds)
            cut = rng.randrange(len(other) + 1)
            b = b[:at] + other[cut:]
        elif op == 9:
            b[at:at] = rng.choice(INTERESTING_TEXT)
        elif op == 10 and n >= 2:  # swap two blocks
            i, j = sorted(rng.sample(range(n), 2))
            k = rng.randint(1, min(16, j - i) or 1)
            b[i : i + k], b[j : j + k] = b[j : j + k], b[i : i + k]
        else:  # arithmetic on a byte
            if n:
                i = rng.randrange(n)
                b[i] = (b[i] + rng.randint(-16, 16)) & 0xFF
        if len(b) > max_len:
            del b[max_len:]
    return bytes(b)


def _f32(x: float) -> float:
    if math.isfinite(x) and abs(x) > 3.4e38:
        return math.copysign(math.inf, x)
    return x


# -- targets ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    """One parser under test.

    Attributes
    ----------
    name : str
    declared : tuple of exception types
        What the parser may raise.
    make : callable
        ``make() -> (generate, run)`` in the child: ``generate(rng) -> input`` and
        ``run(input) -> None``.
    in_memory : bool
        An in-memory parser of ours (the >= 1e6 inputs goal applies).
    default_inputs : int
        Inputs when ``--inputs`` is not given.
    """

    name: str
    declared: Callable[[], tuple[type[BaseException], ...]]
    make: Callable[[], tuple[Callable[[random.Random], Any], Callable[[Any], None]]]
    in_memory: bool = True
    default_inputs: int = 1_000_000
    doc: str = ""
    hang_s: float = HANG_S
    stall_s: float | None = None  # library targets: per-input time limit, as their importer


def _envelope_target():
    import numpy as np

    from groundstation.bus.envelope import Envelope, Header, decode, encode, from_bytes, to_bytes
    from groundstation.bus.topics import TOPICS

    good = [
        Envelope(
            "samples.imu",
            Header("imu_sample", 1, 7, 123, 456, 9),
            {"t_station_ns": 42},
            {"accel_mps2": np.zeros(3), "gyro_radps": np.ones(3)},
        ),
        Envelope(
            "mesh",
            Header("mesh", 1, 0, 1, 2, 3),
            {"fit_index": 3},
            {
                "vertices": np.zeros((4, 3), np.float32),
                "triangles": np.array([[0, 1, 2], [1, 2, 3]], np.int32),
                "vertex_std": np.zeros(4, np.float32),
            },
        ),
        Envelope(
            "status",
            Header("status", 1, 5, 0),
            {"process": "x", "state": "y", "topics": {"a": {"b": [1, 2.5, None, True]}}},
        ),  # fmt: skip
    ]
    frames = [[bytes(f) for f in encode(e)] for e in good]
    blobs = [to_bytes(e) for e in good]
    metas = [f[2] for f in frames]

    def structured_meta(rng: random.Random) -> bytes:
        kind = rng.randrange(5)
        if kind == 0:
            d = rng.randint(1, 5000)
            return b'{"a":[],"p":{"x":' + b"[" * d + b"]" * d + b"}}"
        if kind == 1:
            return b'{"a":[],"p":{"x":' + b"9" * rng.randint(15, 6000) + b"}}"
        if kind == 2:
            sizes = (0, 1, 3, 2**31, 2**40, 2**62, 2**70)
            dims = [rng.choice(sizes) for _ in range(rng.randint(1, 12))]
            return json.dumps({"a": [["accel_mps2", "<f8", dims]], "p": {}}).encode()
        if kind == 3:
            return json.dumps({"a": [[str(i), "<u1", [0]] for i in range(rng.randint(0, 400))],
                               "p": {}}).encode()  # fmt: skip
        return b'{"a":[],"p":{"x":' + rng.choice(INTERESTING_TEXT) + b"}}"

    def generate(rng: random.Random) -> Any:
        r = rng.random()
        if r < 0.15:
            return ("blob", mutate(rng.choice(blobs), rng, blobs))
        f = list(rng.choice(frames))
        if r < 0.35:
            f[2] = structured_meta(rng)
            f = f[:3] + ([b""] * rng.randint(0, 2) if rng.random() < 0.5 else f[3:])
        else:
            i = rng.randrange(len(f))
            f[i] = mutate(f[i], rng, metas if i == 2 else ())
            if rng.random() < 0.1:
                f = f[: rng.randint(0, len(f))] + [b"x"] * rng.randint(0, 2)
        return ("frames", f)

    def run(x: Any) -> None:
        kind, data = x
        if kind == "blob":
            from_bytes(data, TOPICS)
        else:
            decode(data, TOPICS if len(data) % 2 else None)

    return generate, run


def _envelope_errors():
    from groundstation.bus.errors import EnvelopeError

    return (EnvelopeError,)


def _publishable(d: Any) -> None:
    from groundstation.bus.envelope import encode

    encode(d.envelope(0, 1))  # a sample a worker could not publish would kill it


def _natnet_target():
    from firmware_bridge.natnet import (
        SUPPORTED_VERSIONS,
        AnalogDevice,
        FrameExtras,
        FrameOfData,
        LabeledMarker,
        MarkerSet,
        RigidBody,
        ServerInfo,
        Skeleton,
        encode_frame_of_data,
        encode_server_info,
        parse_packet,
    )
    from groundstation.acquisition.decoders import NatNetStreamDecoder

    body = RigidBody(1, (0.5, 1.0, -0.25), (0.0, 0.0, 0.0, 1.0), 0.0002, True)
    extras = FrameExtras(
        marker_sets=(MarkerSet("ms", ((1.0, 2.0, 3.0),)),),
        other_markers=((0.0, 0.0, 0.0),),
        skeletons=(Skeleton(3, (body,)),),
        labeled_markers=(LabeledMarker(5, (1.0, 1.0, 1.0)),),
        force_plates=(AnalogDevice(1, ((1.0, 2.0),)),),
        devices=(AnalogDevice(2, ((3.0,),)),),
    )
    seeds = []
    for v in SUPPORTED_VERSIONS:
        seeds.append((v, encode_frame_of_data(FrameOfData(7, (body, body), 12.5), v)))
        seeds.append((v, encode_frame_of_data(FrameOfData(8, (body,), 1.0), v, extras)))
    info = ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10**7, 1511, True, "239.255.42.99")
    seeds.append(((4, 1), encode_server_info(info)))
    raw = [s[1] for s in seeds]

    def generate(rng: random.Random) -> Any:
        version, data = rng.choice(seeds)
        if rng.random() < 0.1:
            version = rng.choice(SUPPORTED_VERSIONS)
        data = mutate(data, rng, raw)
        if rng.random() < 0.5 and len(data) >= 4:  # keep the header's byte count consistent
            data = data[:2] + struct.pack("<H", (len(data) - 4) & 0xFFFF) + data[4:]
        return version, data

    decoders = {v: NatNetStreamDecoder(v) for v in SUPPORTED_VERSIONS}

    def run(x: Any) -> None:
        version, data = x
        dec = decoders[version]
        for d in dec.feed(data, 1_000_000_000):  # never raises
            _publishable(d)
        if dec.version != version:
            decoders[version] = NatNetStreamDecoder(version)
        parse_packet(data, version)  # NatNetParseError is declared

    return generate, run


def _natnet_errors():
    from firmware_bridge.natnet.records import NatNetParseError

    return (NatNetParseError,)


def _mavlink_target():
    from pymavlink.dialects.v20 import common as mavlink

    from firmware_bridge.mavlink import MavlinkCodec
    from firmware_bridge.mavlink.messages import (
        AttitudeSample,
        Heartbeat,
        ImuSample,
        MocapPose,
        Timesync,
    )
    from groundstation.acquisition.decoders import MavlinkStreamDecoder

    tx = MavlinkCodec(1, 1)
    stream = b"".join(
        tx.encode(r)
        for r in (
            Heartbeat(2, 12, 0, 0, 4),
            ImuSample((0.1, 0.2, -9.8), (0.01, 0.0, 0.02), time_source_ns=5_000_000),
            AttitudeSample((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), time_source_ns=5_000_000),
            Timesync(tc1=4_000_000, ts1=1_000_000),
            MocapPose((1.0, 0.0, 0.0, 0.0), (1.0, 2.0, -3.0), time_source_ns=6_000_000),
        )
    )
    ids = sorted(mavlink.mavlink_map)
    hot = [105, 31, 30, 26, 0, 111, 138, 77, 76, 69, 61]  # what the decoder maps to samples

    def valid_frame(rng: random.Random) -> bytes:
        """A CRC-valid MAVLink 2 frame of a known id with a random (interesting) payload."""
        msgid = rng.choice(hot) if rng.random() < 0.6 else rng.choice(ids)
        cls = mavlink.mavlink_map[msgid]
        full = cls.unpacker.size
        n = rng.choice((full, rng.randint(0, full)))
        payload = bytearray(rng.randbytes(n))
        for _ in range(rng.randint(0, 3)):  # interesting numbers in the fields
            if n >= 8:
                at = rng.randrange(n - 7)
                x = rng.choice(INTERESTING_FLOATS)
                payload[at : at + 8] = (
                    struct.pack("<d", x) if rng.random() < 0.3
                    else rng.choice(INTERESTING_INTS).to_bytes(8, "little")
                )  # fmt: skip
        header = bytes([0xFD, n, 0, 0, rng.randrange(256), rng.choice((1, 1, 2, 255)), 1])
        header += msgid.to_bytes(3, "little")
        crc = mavlink.x25crc(header[1:] + bytes(payload))
        crc.accumulate(bytes([cls.crc_extra]))
        return header + bytes(payload) + struct.pack("<H", crc.crc)

    def generate(rng: random.Random) -> Any:
        r = rng.random()
        if r < 0.45:
            data = b"".join(valid_frame(rng) for _ in range(rng.randint(1, 6)))
        elif r < 0.9:
            data = mutate(stream, rng)
        else:
            data = rng.randbytes(rng.randint(0, 600))
        cuts = sorted(rng.randrange(len(data) + 1) for _ in range(rng.randint(0, 3)))
        recv = rng.choice((0, 1, 10**18, 2**63 - 1, rng.randrange(2**63)))
        return data, cuts, recv

    state = {"dec": MavlinkStreamDecoder(), "n": 0}

    def run(x: Any) -> None:
        data, cuts, recv = x
        state["n"] += 1
        if state["n"] % 1000 == 0:  # a long-lived decoder, as in a session, but not for ever
            state["dec"] = MavlinkStreamDecoder()
        dec = state["dec"]
        prev = 0
        for c in [*cuts, len(data)]:
            for d in dec.feed(data[prev:c], recv):
                _publishable(d)
            prev = c
        dec.health_payload(True)

    return generate, run


def _mcap_target():
    import tempfile
    import warnings

    from groundstation.acquisition import layout
    from groundstation.acquisition.reader import Recording, TruncatedRecordingWarning
    from groundstation.acquisition.recorder import Recorder

    warnings.simplefilter("ignore", TruncatedRecordingWarning)
    seeds = []
    with tempfile.TemporaryDirectory() as d:
        for compression in ("zstd", "none"):
            path = Path(d) / f"{compression}.mcap"
            with Recorder(
                path,
                metadata=layout.station_metadata(station_version="x", created_by="fuzz"),
                max_chunk_span_ns=20_000_000,
                compression=compression,
            ) as rec:
                for i in range(12):
                    t = 10**9 + i * 5_000_000
                    topic = layout.RAW_MAVLINK_TOPIC if i % 3 else layout.RAW_NATNET_TOPIC
                    rec.write(bytes([i]) * 24, topic, t, t, source="fuzz")
                rec.add_truth({"scene": {"objects": []}})
            seeds.append(path.read_bytes())

    def refresh_crcs(data: bytearray) -> None:
        """Recompute chunk CRCs so that mutations reach the records inside."""
        pos = 8
        while pos + 9 <= len(data):
            op, length = struct.unpack_from("<BQ", data, pos)
            body = pos + 9
            if op == 0x06 and body + 40 <= len(data):
                usize, _crc, clen = struct.unpack_from("<QII", data, body + 16)
                rstart = body + 32 + clen + 8
                if clen == 0 and rstart + usize <= len(data):  # uncompressed: easy to redo
                    crc = zlib.crc32(bytes(data[rstart : rstart + usize]))
                    struct.pack_into("<I", data, body + 24, crc)
            if length > len(data):
                break
            pos = body + length

    def generate(rng: random.Random) -> bytes:
        data = bytearray(mutate(rng.choice(seeds), rng, seeds))
        if rng.random() < 0.5:
            refresh_crcs(data)
        return bytes(data)

    def run(data: bytes) -> None:
        with Recording(data) as rec:
            rec.verify()
            for _ in rec.messages():
                pass
            rec.metadata()
            rec.truth()
            rec.damage_text()

    return generate, run


def _groundstation_errors():
    from groundstation.errors import GroundstationError

    return (GroundstationError,)


def _csv_target():
    from collections import Counter as _Counter

    from groundstation.acquisition.importers.csv_imu import (
        GT_COLUMNS,
        GT_POSITION,
        IMU_COLUMNS,
        convert_xsens,
        parse_numeric_csv,
    )

    rows = [f"{i / 120:.6f},1.5,-2.0,{i * 0.1:.3f},0.1,0.2,9.81,0.5,-0.5,1.0" for i in range(12)]
    imu = ("\n".join([",".join(IMU_COLUMNS), *rows]) + "\n").encode()
    gt_cols = GT_COLUMNS + GT_POSITION
    gt_rows = [f"{i / 10:.2f},10.0,1.0,-1.0,{i},0.5,-0.2" for i in range(6)]
    gt = ("\n".join([",".join(gt_cols), *gt_rows]) + "\n").encode()
    seeds = [imu, gt]

    def generate(rng: random.Random) -> Any:
        which = rng.randrange(2)
        return which, mutate(seeds[which], rng, seeds)

    def run(x: Any) -> None:
        which, data = x
        text = data.decode("utf-8", "surrogateescape")
        if which == 0:
            cols = parse_numeric_csv(text, IMU_COLUMNS, _Counter())
            convert_xsens(cols).validate()
        else:
            parse_numeric_csv(text, gt_cols, _Counter())

    return generate, run


def _import_errors():
    from groundstation.acquisition.importers import ImportDataError

    return (ImportDataError,)


def _tlog_target():
    from collections import Counter as _Counter

    from firmware_bridge.mavlink import MavlinkCodec
    from firmware_bridge.mavlink.messages import Heartbeat, ImuSample
    from groundstation.acquisition.importers.tlog import read_tlog

    tx = MavlinkCodec(1, 1)
    seed = b"".join(
        struct.pack(">Q", 1_700_000_000_000_000 + i * 5000)
        + tx.encode(Heartbeat(2, 12, 0, 0, 4) if i % 4 == 0 else ImuSample((0, 0, -9.8), (0, 0, 0)))
        for i in range(8)
    )

    def generate(rng: random.Random) -> bytes:
        return mutate(seed, rng)

    def run(data: bytes) -> None:
        for _ in read_tlog(data, _Counter()):
            pass

    return generate, run


def _ulog_target():
    from groundstation.acquisition.importers.ulog import convert_ulog, parse_ulog

    seed = _synthetic_ulog()

    def generate(rng: random.Random) -> bytes:
        return mutate(seed, rng)

    def run(data: bytes) -> None:
        convert_ulog(parse_ulog(data)).validate()

    return generate, run


def _synthetic_ulog(n: int = 40) -> bytes:
    """A small valid ULog (sensor_combined, vehicle_attitude) built from the ULog spec."""

    def msg(kind: str, payload: bytes) -> bytes:
        return struct.pack("<HB", len(payload), ord(kind)) + payload

    out = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 1_000_000))
    out += msg("B", bytes(40))
    out += msg("F", b"sensor_combined:uint64_t timestamp;float[3] gyro_rad;"
                    b"float[3] accelerometer_m_s2")  # fmt: skip
    out += msg("F", b"vehicle_attitude:uint64_t timestamp;float[4] q")
    out += msg("A", struct.pack("<BH", 0, 1) + b"sensor_combined")
    out += msg("A", struct.pack("<BH", 0, 2) + b"vehicle_attitude")
    for i in range(n):
        t = 2_000_000 + i * 4000
        out += msg("D", struct.pack("<HQ6f", 1, t, 0.01, 0.0, 0.0, 0.1, 0.0, -9.81))
        out += msg("D", struct.pack("<HQ4f", 2, t, 1.0, 0.0, 0.0, 0.0))
    return bytes(out)


TARGETS: dict[str, Target] = {
    t.name: t
    for t in (
        Target("envelope", _envelope_errors, _envelope_target),
        Target("natnet", _natnet_errors, _natnet_target),
        Target("mavlink", lambda: (), _mavlink_target),
        Target("mcap", _groundstation_errors, _mcap_target),
        Target("csv", _import_errors, _csv_target),
        Target("tlog", lambda: (), _tlog_target),
        Target("ulog", _import_errors, _ulog_target, in_memory=False, default_inputs=5_000,
               doc="pyulog, a third-party parser the importer runs under a time limit",
               stall_s=0.5),
    )
}  # fmt: skip
