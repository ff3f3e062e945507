"""Pure MAVLink 2 codec: records <-> bytes, with framing, resync, signing policy and counters.

Encoding and per-frame decoding (CRC-extra check, signature check, payload unpacking) are done by
pymavlink's generated ``common`` dialect class ``MAVLink``. The byte loop that finds frames is our
own: pymavlink's ``parse_buffer`` consumes the whole length a header claims when the CRC fails,
so a single truncated frame also destroys the frame after it. Here a rejected candidate only skips
its start byte and the scan resumes one byte later (the resync of the MAVLink C parser's
``mavlink_frame_char`` at a finer grain), so every intact frame after damage is recovered.

No sockets, threads, files or clock reads (except :func:`signing_timestamp_now` when outgoing
signing is enabled without an explicit timestamp).
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before any pymavlink import (mavutil reads it; harmless here)

import operator  # noqa: E402
import re  # noqa: E402
import struct  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

from pymavlink.dialects.v20 import common as _mavlink  # noqa: E402

from firmware_bridge.errors import ProtocolError  # noqa: E402
from firmware_bridge.mavlink.messages import Record, from_mavlink, to_mavlink  # noqa: E402
from firmware_bridge.mavlink.signing import (  # noqa: E402
    UPLINK_MESSAGE_IDS,
    parse_signing_key,
    signing_timestamp_now,
)

_STX_V2 = 0xFD  # MAVLink 2 start byte
_STX_V1 = 0xFE  # MAVLink 1 start byte
_STX = re.compile(b"[\xfd\xfe]")
_SIGNATURE_LEN = 13  # link id (1) + timestamp (6) + signature (6)
_KNOWN_IDS = frozenset(_mavlink.mavlink_map)


@dataclass
class DecodeStats:
    """Counters of one decoder; never reset by the codec.

    Attributes
    ----------
    frames : int
        Frames accepted (checksum and, where required, signature valid), including unknown ids.
    bytes : int
        Bytes fed to :meth:`MavlinkCodec.decode`.
    crc_errors : int
        Damaged frames: candidates failing the checksum. A false start byte inside an already
        rejected candidate is not counted again (its bytes count as garbage).
    garbage_bytes : int
        Bytes that belong to no accepted frame (noise, damaged frames).
    unknown : int
        Frames with a message id outside the ``common`` dialect (or unsupported incompat flags),
        skipped.
    unhandled : int
        Valid ``common`` frames that map to no record (e.g. SYS_STATUS), skipped.
    rejected_signature : int
        Command-uplink frames rejected by the signing policy (unsigned, wrong key, replayed).
    seq_gaps : dict[(int, int), int]
        Frames missing in the sequence numbers, per (system id, component id).
    per_type : dict[str, int]
        Accepted frames per message name ("HIGHRES_IMU", "UNKNOWN_42424", ...).
    """

    frames: int = 0
    bytes: int = 0
    crc_errors: int = 0
    garbage_bytes: int = 0
    unknown: int = 0
    unhandled: int = 0
    rejected_signature: int = 0
    seq_gaps: dict[tuple[int, int], int] = field(default_factory=dict)
    per_type: dict[str, int] = field(default_factory=dict)

    @property
    def lost(self) -> int:
        """Total frames missing in sequence numbers over all senders."""
        return sum(self.seq_gaps.values())

    def copy(self) -> DecodeStats:
        """Independent snapshot (dicts copied)."""
        return DecodeStats(
            self.frames, self.bytes, self.crc_errors, self.garbage_bytes, self.unknown,
            self.unhandled, self.rejected_signature, dict(self.seq_gaps), dict(self.per_type),
        )  # fmt: skip


def _crc_accumulate(crc: int, byte: int) -> int:
    """One step of the MAVLink X.25 / CRC-16-MCRF4XX checksum (mavlink checksum.h)."""
    tmp = (byte ^ (crc & 0xFF)) & 0xFF
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    return ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF


def _crc_matches_known(buf: bytearray, pos: int, flen: int) -> bool:
    """True if ``buf[pos:pos+flen]`` is a frame of a known id whose checksum (with its CRC-extra)
    matches. Pure check: no counters, no signing state."""
    v2 = buf[pos] == _STX_V2
    msgid = (buf[pos + 7] | (buf[pos + 8] << 8) | (buf[pos + 9] << 16)) if v2 else buf[pos + 5]
    cls = _mavlink.mavlink_map.get(msgid)
    if cls is None:
        return False
    end = pos + flen - 2 - (_SIGNATURE_LEN if v2 and buf[pos + 2] & 0x01 else 0)
    crc = _mavlink.x25crc(bytes(buf[pos + 1 : end]))
    crc.accumulate(bytes([cls.crc_extra]))
    return crc.crc == (buf[end] | (buf[end + 1] << 8))


#: Every value of ``_crc_accumulate(c, b) ^ (c >> 8)`` over all bytes ``b`` (any ``c``).
_LAST_STEP_TERMS = frozenset(_crc_accumulate(0, b) for b in range(256))


class _Layout:
    """What decoding one message type needs, taken from its pymavlink class once."""

    __slots__ = ("cls", "crc_extra", "size", "unpack", "pick", "patches")

    def __init__(self, cls: type) -> None:
        self.cls = cls
        self.crc_extra = bytes([cls.crc_extra])
        self.size = cls.unpacker.size
        self.unpack = cls.unpacker.unpack
        lengths = cls.lengths
        # first index in the unpacked tuple of each field, in declared order
        tips = [sum(lengths[:o]) for o in cls.orders]
        get = operator.itemgetter(*tips)
        self.pick = get if len(tips) > 1 else (lambda t: (get(t),))
        # fields that are not one plain value: arrays (a list) and strings (NUL-stripped)
        self.patches = tuple(
            (k, tip, lengths[o])
            for k, (tip, o) in enumerate(zip(tips, cls.orders, strict=True))
            if lengths[o] != 1 or cls.fieldtypes[k] == "char"
        )


_LAYOUTS: dict[int, _Layout] = {}


def _layout(msgid: int) -> _Layout:
    lay = _LAYOUTS.get(msgid)
    if lay is None:
        lay = _LAYOUTS[msgid] = _Layout(_mavlink.mavlink_map[msgid])
    return lay


def _crc16(data: bytes) -> int:
    """X.25 checksum of ``data`` (pymavlink's ``x25crc``, C-accelerated when it is)."""
    return _mavlink.x25crc(data).crc


def _decode_plain_v2(frame: bytearray, msgid: int) -> object | None:
    """pymavlink's ``MAVLink.decode`` for an unsigned MAVLink 2 frame of a known id without
    incompat flags, on a receiver without a signing key (the replay and the usual live link).

    Same message object, fields and checks (length, checksum with CRC-extra, zero-padded
    truncated payload, arrays, NUL-stripped strings) as the generated decoder, none of whose
    signing state applies to such a frame; None where it raises ``MAVError``. It skips the
    generic decoder's per-call header unpacking and re-slicing, which dominated replay time.
    """
    lay = _layout(msgid)
    mlen = frame[1]
    if mlen != len(frame) - 12:
        return None
    crc = frame[-2] | (frame[-1] << 8)
    if crc != _crc16(bytes(frame[1:-2]) + lay.crc_extra):
        return None
    payload = bytes(frame[10:-2])
    if len(payload) < lay.size:
        payload += bytes(lay.size - len(payload))  # MAVLink 2 trims trailing zero bytes
    try:
        t = lay.unpack(payload[: lay.size])
        values = lay.pick(t)
        if lay.patches:
            values = list(values)
            for k, tip, n in lay.patches:
                v = t[tip]
                if isinstance(v, bytes):  # char fields, as pymavlink strips them
                    values[k] = v.rstrip(b"\x00")
                elif n != 1:
                    values[k] = list(t[tip : tip + n])
        msg = lay.cls(*values)
    except Exception:  # struct.error or a constructor error: MAVError in pymavlink
        return None
    msg._signed = False
    msg._msgbuf = frame
    msg._payload = frame[6:-2]
    msg._crc = crc
    msg._header = _mavlink.MAVLink_header(msgid, 0, frame[3], mlen, frame[4], frame[5], frame[6])
    return msg


class MavlinkCodec:
    """Encode records to MAVLink 2 frames and decode byte chunks to records.

    Parameters
    ----------
    system_id, component_id : int
        Our MAVLink address in outgoing frames (station: 255/190, MAV_COMP_ID_MISSIONPLANNER).
    signing_key : bytes or None
        32-byte secret (see :func:`load_signing_key`). None disables signing entirely.
    require_signed : bool
        With a key: reject command-uplink frames (MANUAL_CONTROL, COMMAND_LONG, ATT_POS_MOCAP) that
        are unsigned. Wrongly signed uplink frames are rejected whenever a key is set. Telemetry is
        never required to be signed.
    sign_outgoing : bool
        With a key: sign every frame we encode.
    signing_link_id : int
        Link id written into our signatures.
    signing_timestamp : int or None
        First outgoing signing timestamp (10 us since 2015-01-01); None reads the wall clock once.

    Notes
    -----
    ``encode`` and ``decode`` use separate pymavlink instances, so one thread may encode while
    another decodes; neither method is re-entrant on its own.
    """

    def __init__(
        self,
        system_id: int = 255,
        component_id: int = 190,
        signing_key: bytes | None = None,
        require_signed: bool = False,
        sign_outgoing: bool = False,
        *,
        signing_link_id: int = 0,
        signing_timestamp: int | None = None,
    ) -> None:
        if not (0 <= system_id <= 255 and 0 <= component_id <= 255):
            raise ProtocolError(
                f"system_id/component_id must be in 0..255, got {system_id}/{component_id}"
            )
        if (require_signed or sign_outgoing) and signing_key is None:
            raise ProtocolError(
                "require_signed/sign_outgoing need a signing_key",
                hint="load one with firmware_bridge.mavlink.signing.load_signing_key(path)",
            )
        self.system_id = system_id
        self.component_id = component_id
        self.require_signed = require_signed
        self._tx = _mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._rx = _mavlink.MAVLink(None)
        self.signing_key = None if signing_key is None else parse_signing_key(signing_key)
        if self.signing_key is not None:
            self._rx.signing.secret_key = self.signing_key
            self._rx.signing.allow_unsigned_callback = self._allow_unverified
            if sign_outgoing:
                self._tx.signing.secret_key = self.signing_key
                self._tx.signing.sign_outgoing = True
                self._tx.signing.link_id = signing_link_id
                self._tx.signing.timestamp = (
                    signing_timestamp_now() if signing_timestamp is None else signing_timestamp
                )
        self.stats = DecodeStats()
        self._buf = bytearray()
        self._offset = 0  # stream offset of self._buf[0]
        self._bad_until = 0  # stream offset where the last rejected candidate ends
        self._last_seq: dict[tuple[int, int], int] = {}
        self._frame_signed = False

    # --- encoding -----------------------------------------------------------------------

    def encode(self, record: Record) -> bytes:
        """One MAVLink 2 frame (signed if configured) for a record; sequence number advances.

        Raises
        ------
        ProtocolError
            A field does not fit its wire type.
        """
        msg = to_mavlink(record, self._tx)
        try:
            frame = msg.pack(self._tx)
        except struct.error as exc:
            raise ProtocolError(f"cannot encode {record!r}: {exc}") from exc
        self._tx.seq = (self._tx.seq + 1) & 0xFF
        return frame

    # --- decoding -----------------------------------------------------------------------

    @property
    def pending_bytes(self) -> int:
        """Bytes buffered while waiting for the rest of a frame."""
        return len(self._buf)

    def decode(self, data: bytes, recv_ns: int) -> list[Record]:
        """Feed a chunk of bytes (any split); return the records completed by it.

        Parameters
        ----------
        data : bytes
            Next bytes from the link. Partial frames are kept for the next call.
        recv_ns : int
            Station monotonic receive time of this chunk, ns (stamped on every record).

        Never raises for bad bytes: damage, noise, unknown ids and rejected signatures are
        skipped and counted in :attr:`stats`.
        """
        st = self.stats
        st.bytes += len(data)
        buf = self._buf
        buf += data
        out: list[Record] = []
        pos, n = 0, len(buf)
        while True:
            m = _STX.search(buf, pos)
            if m is None:
                st.garbage_bytes += n - pos
                pos = n
                break
            start = m.start()
            st.garbage_bytes += start - pos
            pos = start
            if n - pos < 3:
                break
            if buf[pos] == _STX_V2:
                flen = buf[pos + 1] + 12 + (_SIGNATURE_LEN if buf[pos + 2] & 0x01 else 0)
            else:
                flen = buf[pos + 1] + 8
            if n - pos < flen:
                break
            hidden = self._hides_known_frame(buf, pos, flen, n)
            if hidden is None:
                break  # a candidate inside this weakly checked one still needs bytes
            if not hidden and self._frame(buf[pos : pos + flen], recv_ns, out):
                pos += flen
                continue
            # Rejected candidate: count the damage once, then resync one byte further on.
            abs_start = self._offset + pos
            if abs_start >= self._bad_until:
                st.crc_errors += 1
                self._bad_until = abs_start + flen
            st.garbage_bytes += 1
            pos += 1
        del buf[:pos]
        self._offset += pos
        return out

    def _frame(self, frame: bytearray, recv_ns: int, out: list[Record]) -> bool:
        """Handle one candidate frame; False if it is not a valid frame (checksum)."""
        st = self.stats
        if frame[0] == _STX_V2:
            msgid = frame[7] | (frame[8] << 8) | (frame[9] << 16)
            incompat = frame[2]
            seq, sysid, compid = frame[4], frame[5], frame[6]
        else:
            msgid, incompat = frame[5], 0
            seq, sysid, compid = frame[2], frame[3], frame[4]
        signed = bool(incompat & 0x01)
        if msgid not in _KNOWN_IDS:
            if not self._plausible_unknown(frame, signed):
                return False
            name = f"UNKNOWN_{msgid}"
            st.unknown += 1
        else:
            self._frame_signed = signed
            signing = self._rx.signing
            rejected_before, badsig_before = signing.reject_count, signing.badsig_count
            stream = (frame[-13], sysid, compid) if signed else None
            last_ts = signing.stream_timestamps.get(stream) if stream else None
            if self.signing_key is None and incompat == 0 and frame[0] == _STX_V2:
                msg = _decode_plain_v2(frame, msgid)  # what self._rx.decode does, faster
            else:
                try:
                    msg = self._rx.decode(frame)
                except Exception:  # MAVError, or anything else pymavlink raises on bad bytes
                    msg = None
            if stream is not None and signing.badsig_count != badsig_before:
                # pymavlink stores a stream's timestamp *before* it checks the signature: one
                # forged frame with timestamp 2**48-1 would make every genuine frame after it a
                # "replay" (even a forged telemetry frame, accepted unverified). Keep only
                # verified timestamps, as the MAVLink C library's mavlink_signature_check does.
                if last_ts is None:
                    signing.stream_timestamps.pop(stream, None)
                else:
                    signing.stream_timestamps[stream] = last_ts
            if msg is None:
                if signing.reject_count != rejected_before:
                    st.rejected_signature += 1
                    return True  # a real frame (checksum passed): skip it whole
                return False
            name = msg.get_type()
            if incompat & ~0x01:
                st.unknown += 1  # unsupported incompat flag: cannot be interpreted safely
            else:
                try:
                    rec = from_mavlink(msg, recv_ns)
                except Exception:
                    rec = None
                if rec is None:
                    st.unhandled += 1
                else:
                    out.append(rec)
        st.frames += 1
        st.per_type[name] = st.per_type.get(name, 0) + 1
        key = (sysid, compid)
        last = self._last_seq.get(key)
        if last is not None and seq != last:
            gap = (seq - last - 1) & 0xFF
            if gap:
                st.seq_gaps[key] = st.seq_gaps.get(key, 0) + gap
        elif last is None:
            st.seq_gaps.setdefault(key, 0)
        self._last_seq[key] = seq
        return True

    @staticmethod
    def _msgid(buf: bytearray, pos: int) -> int:
        if buf[pos] == _STX_V2:
            return buf[pos + 7] | (buf[pos + 8] << 8) | (buf[pos + 9] << 16)
        return buf[pos + 5]

    @classmethod
    def _hides_known_frame(cls, buf: bytearray, pos: int, flen: int, n: int) -> bool | None:
        """Would accepting the unknown-id candidate at ``pos`` swallow a valid known frame?

        An unknown-id candidate is only checked against 256 possible CRC-extra bytes, so a false
        start byte in noise passes with p = 1/256 and, accepted, would skip up to 280 bytes of
        good frames after it (the cause of ``test_random_damage...`` failing with seed 79996:
        a noise candidate "UNKNOWN_154" hid 4 intact frames). A known-id frame carries a full
        16-bit check with its CRC-extra, so when one starts inside the candidate the candidate is
        the noise. False for known ids (their check is strong) and when nothing is hidden; None
        when an inner candidate is not complete yet (decide once more bytes arrive).
        """
        if cls._msgid(buf, pos) in _KNOWN_IDS:
            return False
        inner = pos + 1
        end = pos + flen
        while True:
            m = _STX.search(buf, inner, end)
            if m is None:
                return False
            inner = m.start()
            if n - inner < 12:  # not even a header yet
                return None
            if buf[inner] == _STX_V2:
                ilen = buf[inner + 1] + 12 + (_SIGNATURE_LEN if buf[inner + 2] & 0x01 else 0)
            else:
                ilen = buf[inner + 1] + 8
            if n - inner < ilen:
                return None
            if _crc_matches_known(buf, inner, ilen):
                return True
            inner += 1

    @staticmethod
    def _plausible_unknown(frame: bytearray, signed: bool) -> bool:
        """Accept an unknown-id frame if some CRC-extra byte (0..255) makes its checksum match.

        We lack the message's CRC-extra, so noise passes with probability 256/65536; this keeps a
        false start byte in noise from swallowing the frames after it.
        """
        end = len(frame) - 2 - (_SIGNATURE_LEN if signed else 0)
        crc_wire = frame[end] | (frame[end + 1] << 8)
        crc = _mavlink.x25crc(frame[1:end]).crc
        # _crc_accumulate(crc, extra) = (crc >> 8) ^ G(extra ^ (crc & 0xFF)) with G a fixed map,
        # so "some extra matches" is a set lookup (same answer as trying all 256 values).
        return (crc_wire ^ (crc >> 8)) in _LAST_STEP_TERMS

    def _allow_unverified(self, mav: object, msgid: int) -> bool:
        """pymavlink hook for frames without a valid signature while a key is set."""
        if msgid not in UPLINK_MESSAGE_IDS:
            return True  # telemetry need not be signed
        if self._frame_signed:
            return False  # signed, but wrong key / replayed timestamp
        return not self.require_signed
