"""MCAP chunk records decoded with bounded sizes (pure: bytes in, records out).

The mcap package's ``breakup_chunk`` trusts the sizes a chunk declares: a 2**63 uncompressed size
raised OverflowError, a cut records length MemoryError, a zstd frame declaring a huge content
size would allocate it, and an unknown compression passed the bytes through as records. Here a
chunk is checked before anything is allocated (sizes <= :data:`MAX_CHUNK_BYTES`, a zstd frame may
not declare more than the chunk header, decompression output capped), its CRC verified, and its
records parsed with bounds; every problem is a :class:`ChunkDamage` naming it. The recording
reader (:mod:`groundstation.acquisition.reader`) turns those into a damage report.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel

_RECORD_PREFIX = struct.Struct("<BQ")  # opcode u8, length u64 (MCAP spec "Records")
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
#: Largest chunk (compressed or not) decoded; the recorder writes 256 KiB chunks.
MAX_CHUNK_BYTES = 256 * 1024 * 1024


class ChunkDamage(Exception):
    """A chunk (or a record in it) cannot be decoded; the message names the problem."""


@dataclass(frozen=True, slots=True)
class ChunkMessage:
    """One Message record of a chunk (MCAP spec "Message")."""

    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    """Chunk records, decompressed with the output capped at the declared ``size``."""
    if compression == "":
        return data
    try:
        if compression == "zstd":
            import zstandard

            declared = zstandard.frame_content_size(data)
            if declared > size:  # zstd would allocate what the frame declares
                raise ChunkDamage(f"zstd frame declares {declared} bytes, chunk header says {size}")
            # max_output_size=0 would mean "no limit" for a frame without a content size
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=max(size, 1))
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size)
    except ImportError as exc:
        raise ChunkDamage(f"{compression} chunks need a package that is missing: {exc}") from None
    except ChunkDamage:
        raise
    except Exception as exc:  # noqa: BLE001 - zstd/lz4 raise their own error types
        raise ChunkDamage(f"{compression} decompression failed: {str(exc)[:100]}") from None
    raise ChunkDamage(f"unknown chunk compression {compression[:20]!r}")


def decode_chunk(body: bytes) -> list[Channel | ChunkMessage]:
    """Decode a chunk record body: bounded sizes, CRC checked; raises :class:`ChunkDamage`."""
    if len(body) < _CHUNK_HEAD.size:
        raise ChunkDamage(f"chunk of {len(body)} bytes is shorter than its header")
    _start, _end, usize, crc, clen = _CHUNK_HEAD.unpack_from(body)
    o = _CHUNK_HEAD.size
    if clen > 64 or o + clen + _U64.size > len(body):
        raise ChunkDamage(f"chunk compression name of {clen} bytes")
    try:
        compression = body[o : o + clen].decode("utf-8")
    except UnicodeDecodeError:
        raise ChunkDamage("chunk compression name is not UTF-8") from None
    o += clen
    (rlen,) = _U64.unpack_from(body, o)
    o += _U64.size
    if rlen != len(body) - o:
        raise ChunkDamage(f"chunk declares {rlen} record bytes but holds {len(body) - o}")
    if usize > MAX_CHUNK_BYTES or rlen > MAX_CHUNK_BYTES:
        raise ChunkDamage(f"chunk of {usize} bytes exceeds the {MAX_CHUNK_BYTES}-byte limit")
    data = _decompress(compression, body[o:], usize)
    if len(data) != usize:
        raise ChunkDamage(f"chunk decompressed to {len(data)} bytes, header says {usize}")
    if crc != 0 and zlib.crc32(data) != crc:
        raise ChunkDamage(f"chunk CRC {zlib.crc32(data):#010x} does not match {crc:#010x}")
    return _chunk_records(data)


def _chunk_records(data: bytes) -> list[Channel | ChunkMessage]:
    out: list[Channel | ChunkMessage] = []
    pos, n = 0, len(data)
    while pos < n:
        if n - pos < _RECORD_PREFIX.size:
            raise ChunkDamage(f"{n - pos} stray bytes at the end of a chunk")
        op, length = _RECORD_PREFIX.unpack_from(data, pos)
        pos += _RECORD_PREFIX.size
        if length > n - pos:
            raise ChunkDamage(f"record {op:#x} of {length} bytes runs past the chunk end")
        if op == Opcode.MESSAGE:
            if length < _MESSAGE_HEAD.size:
                raise ChunkDamage(f"message record of {length} bytes")
            cid, seq, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, pos)
            body = data[pos + _MESSAGE_HEAD.size : pos + length]
            out.append(ChunkMessage(cid, seq, log_time, publish_time, body))
        elif op == Opcode.CHANNEL:
            try:
                out.append(Channel.read(ReadDataStream(io.BytesIO(data[pos : pos + length]))))
            except Exception as exc:  # noqa: BLE001 - mcap's record parser on bad bytes
                raise ChunkDamage(
                    f"channel record: {type(exc).__name__}: {str(exc)[:80]}"
                ) from None
        pos += length
    return out


def message_index_count(body: bytes) -> tuple[int, int] | None:
    """(channel id, number of entries) of a MessageIndex record body, or None if malformed."""
    if len(body) < 6:
        return None
    cid = body[0] | (body[1] << 8)
    (records_len,) = _U32.unpack_from(body, 2)
    if records_len % 16 or 6 + records_len != len(body):
        return None
    return cid, records_len // 16
