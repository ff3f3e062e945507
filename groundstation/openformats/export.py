"""Foxglove channels into recordings: the recorder hook, ``export foxglove`` and replay outputs.

- :class:`FoxgloveWriter`: translate bus messages (:mod:`~groundstation.openformats.foxglove`)
  and write the results through a :class:`~groundstation.acquisition.recorder.Recorder`. The
  recorder process calls it for every message it writes; replay outputs and the exporter too.
- :func:`export_foxglove`: ``groundstation export foxglove OLD.mcap --out NEW.mcap``. NEW holds
  every channel of OLD unchanged (raw bytes, the station's envelopes, metadata, ground truth)
  plus the Foxglove channels translated from them. A recording without decoded samples (the
  bundled SITL logs, imports) has its raw bytes decoded by the replay decoders for the pose,
  IMU, attitude and signal channels. Foxglove channels already in OLD are regenerated, not
  copied.
- :func:`result_envelopes`: the pipeline results of a replay (contact events, observations,
  fits, meshes) as bus envelopes in data-time order, so a replay output recording carries them
  like a live one.
"""

from __future__ import annotations

import dataclasses
import heapq
import json
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from groundstation.acquisition import layout
from groundstation.acquisition.reader import Recording, open_recording
from groundstation.acquisition.recorder import Recorder
from groundstation.bus.envelope import Envelope, Header, from_bytes, to_bytes
from groundstation.bus.topics import TOPICS
from groundstation.config import Config
from groundstation.errors import InputDataError
from groundstation.openformats.channels import CHANNELS, PROTOBUF, schema_data
from groundstation.openformats.foxglove import FoxgloveMessage, FoxgloveTranslator

SAMPLE_TOPICS = ("samples.imu", "samples.attitude", "samples.pose")


class FoxgloveWriter:
    """Translate bus messages and write the Foxglove messages into ``recorder``.

    Parameters
    ----------
    recorder : Recorder
        Open recorder (the caller closes it).
    translator : FoxgloveTranslator
    """

    def __init__(self, recorder: Recorder, translator: FoxgloveTranslator) -> None:
        self.recorder = recorder
        self.translator = translator
        self.written = 0

    def add(self, env: Envelope, log_time_ns: int | None = None) -> list[FoxgloveMessage]:
        """Translate one bus message, write its Foxglove messages and return them."""
        out = self.translator.translate(env, log_time_ns)
        self.write(out)
        return out

    def write(self, messages: Iterable[FoxgloveMessage]) -> None:
        for m in messages:
            ch = CHANNELS[m.topic]
            self.recorder.write_typed(
                m.data,
                m.topic,
                m.log_time_ns,
                m.publish_time_ns,
                schema_name=ch.schema,
                schema_encoding=PROTOBUF,
                schema_data=schema_data(ch.schema),
                message_encoding=PROTOBUF,
            )
            self.written += 1

    def finish(self) -> list[FoxgloveMessage]:
        """Write the translator's final state (last path, last contact cloud)."""
        out = self.translator.finish()
        self.write(out)
        return out


def foxglove_hook(config: Config | None = None):
    """``recorder -> FoxgloveWriter`` for the recorder process, with the session's contact and
    alignment settings (the signal's filter and threshold; defaults when None)."""
    from groundstation.config import load_config

    cfg = config if config is not None else load_config()

    def make(recorder: Recorder) -> FoxgloveWriter:
        return FoxgloveWriter(recorder, FoxgloveTranslator(cfg.contact, cfg.alignment))

    return make


def is_foxglove_channel(topic: str, message_encoding: str) -> bool:
    """True for a Foxglove channel (regenerated, never copied)."""
    return topic.startswith("/") and message_encoding == PROTOBUF


def check_groundstation_recording(rec: Recording, need_raw: bool = False) -> None:
    """Refuse an MCAP file that is not a station recording.

    A station recording has the ``groundstation`` metadata record or channels in the station's
    encodings; with ``need_raw`` it must also hold raw ``raw.mavlink`` / ``raw.natnet`` bytes
    (what replay decodes).

    Raises
    ------
    InputDataError
        Naming the file, what it holds instead, and what to do.
    """
    channels = rec.summary.channels
    ours = [c for c in channels if c.message_encoding in layout.KNOWN_ENCODINGS]
    raw = [c for c in ours if c.topic in (layout.RAW_MAVLINK_TOPIC, layout.RAW_NATNET_TOPIC)]
    listing = ", ".join(sorted({f"{c.topic} ({c.message_encoding or 'no encoding'})"
                                for c in channels})[:8]) or "no channels"  # fmt: skip
    if rec.metadata() is None and not ours:
        raise InputDataError(
            f"{str(rec.path)!r} is an MCAP file but not a groundstation recording "
            f"(no 'groundstation' metadata, channels: {listing})",
            hint="record with 'groundstation live --record' or 'groundstation record', or "
            "convert with 'groundstation import csv|ulog|tlog'",
        )
    if need_raw and not raw:
        raise InputDataError(
            f"{str(rec.path)!r} has no raw.mavlink or raw.natnet channel to replay "
            f"(channels: {listing})",
            hint="replay needs the raw bytes a live session or an import records",
        )


def copy_message(dst: Recorder, msg) -> None:
    """Copy one recorded message of the station's layout (same topic, times, source, metadata)."""
    meta = dict(msg.channel.metadata)
    source = meta.pop(layout.KEY_SOURCE, None)
    meta.pop(layout.KEY_LAYOUT, None)
    dst.write(
        msg.data,
        msg.topic,
        msg.log_time_ns,
        msg.publish_time_ns,
        source=source,
        channel_metadata=meta or None,
    )


@dataclasses.dataclass
class ExportSummary:
    """What :func:`export_foxglove` wrote."""

    copied: int
    skipped: int
    foxglove: dict[str, int]
    decoded_samples: bool
    bad: int = 0


def export_foxglove(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    translator: FoxgloveTranslator | None = None,
    *,
    acquisition=None,
    created_by: str = "groundstation export foxglove",
) -> ExportSummary:
    """Copy ``src`` into ``dst`` with Foxglove channels added (module docstring).

    Raises
    ------
    InputDataError
        ``src`` is not a groundstation recording, or ``dst`` is ``src``.
    RecordingError
        Reading or writing failed.
    """
    from groundstation.acquisition.replay import Window, replay_decoded

    if Path(src).resolve() == Path(dst).resolve():
        raise InputDataError(f"--out {str(dst)!r} is the input file", hint="write a new file")
    translator = translator or FoxgloveTranslator()
    copied = skipped = 0
    with open_recording(src) as rec:
        check_groundstation_recording(rec)
        meta = rec.metadata() or {}
        with Recorder(dst, metadata=meta or None) as out:
            out.add_metadata("groundstation.export", {"created_by": created_by, "source": str(src)})
            truth = rec.truth()
            if truth is not None:
                out.add_truth(truth)
            fox = FoxgloveWriter(out, translator)
            has_samples = any(t in rec.topics() for t in SAMPLE_TOPICS)
            for msg in rec.messages():
                enc = msg.channel.message_encoding
                if is_foxglove_channel(msg.topic, enc) or enc not in layout.KNOWN_ENCODINGS:
                    skipped += 1
                    continue
                copy_message(out, msg)
                copied += 1
                if enc == layout.ENVELOPE_ENCODING:
                    try:
                        env = from_bytes(msg.data)
                    except Exception:  # noqa: BLE001 - a bad blob is copied, not translated
                        translator.bad += 1
                        continue
                    fox.add(env, msg.log_time_ns)
            decoded = False
            if not has_samples:
                decoded = True
                for _msg, samples in replay_decoded(rec, Window(None, None), acquisition):
                    for d in samples:
                        fox.add(d.envelope(0), d.recv_ns)
            fox.finish()
    return ExportSummary(copied, skipped, dict(translator.counts), decoded, translator.bad)


# -- pipeline results as envelopes ----------------------------------------------------------------
def _env(topic: str, seq: int, t_ns: int, payload: dict, arrays: dict) -> Envelope:
    spec = TOPICS[topic]
    return Envelope(topic, Header(spec.type, spec.schema_version, seq, int(t_ns), int(t_ns), 0),
                    payload, arrays)  # fmt: skip


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def result_envelopes(result) -> Iterator[Envelope]:
    """Contact events, observations, fits and new meshes of a ``PipelineResult`` as bus
    envelopes in data-time order (source and receive time = the data time they refer to)."""
    from groundstation.contact.stage import observation_payload

    def events():
        for i, e in enumerate(result.events):
            yield _env("contact.event", i, e.header.source_ns, dict(e.payload), dict(e.arrays))

    def observations():
        for i, o in enumerate(result.observations):
            payload, arrays = observation_payload(o)
            yield _env("observations", i, o.t_ns, payload, arrays)

    def fits():
        mesh_seq = 0
        for i, f in enumerate(result.fits):
            payload = {
                "fit_index": int(f.fit_index),
                "reliable": bool(f.reliable),
                "reasons": [str(r) for r in f.reasons],
                "data_ns": int(f.data_ns),
                "fit_s": float(f.timings.get("total_s", 0.0)),
                "timings": {k: float(v) for k, v in f.timings.items()},
                "hyperparameters": _jsonable(f.hyperparameters),
                "flagged_events": [int(e) for e in f.flagged_events],
            }
            arrays = {
                "ids": np.asarray(f.ids, dtype=np.int64),
                "u": np.asarray(f.u, dtype=np.float64),
                "flags": np.asarray(f.flags, dtype=np.uint8),
            }
            yield _env("mapper.fit", i, f.data_ns, payload, arrays)
            m = f.mesh
            if m is not None and not m.is_empty and f.mesh_fit_index == f.fit_index:
                std = m.std if m.std is not None else np.zeros(len(m.vertices))
                yield _env("mesh", mesh_seq, f.data_ns, {"fit_index": int(f.fit_index)}, {
                    "vertices": np.asarray(m.vertices, dtype=np.float64),
                    "triangles": np.asarray(m.faces, dtype=np.int64),
                    "vertex_std": np.asarray(std, dtype=np.float64),
                })  # fmt: skip
                mesh_seq += 1

    key = lambda env: env.header.source_ns  # noqa: E731
    yield from heapq.merge(events(), observations(), fits(), key=key)


def write_envelope(recorder: Recorder, env: Envelope) -> None:
    """Record a derived envelope at its data time (log and publish time)."""
    t = int(env.header.source_ns)
    recorder.write(to_bytes(env), env.topic, t, t)
