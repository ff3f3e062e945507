"""``replay.mcap``: a replay's output recording, in the station's layout with Foxglove channels.

What ``groundstation replay LOG --out DIR`` writes to ``DIR/replay.mcap``:

- the raw channels of LOG (``raw.mavlink``, ``raw.natnet``, ``raw.pilot``) inside the replayed
  window, unchanged, with LOG's metadata record and ``truth.json``: the file replays again;
- the replay's results as the station's envelopes, at their data time: ``contact.event``,
  ``observations``, ``mapper.fit`` and ``mesh`` (every mesh the replay kept);
- the Foxglove channels (:mod:`~groundstation.openformats.channels`) of the decoded samples
  and of those results.

:class:`ReplayOutput` is filled while the pipeline runs (:meth:`sample` is the in-process
pipeline's ``tap``, so the log is decoded once) and keeps the detector signal and the flown
path for ``report.html``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from groundstation.acquisition import layout
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.recorder import Recorder
from groundstation.bus.envelope import Envelope
from groundstation.config import Config
from groundstation.openformats.export import (
    FoxgloveWriter,
    copy_message,
    result_envelopes,
    write_envelope,
)
from groundstation.openformats.foxglove import FoxgloveTranslator

RAW_COPY = (layout.RAW_MAVLINK_TOPIC, layout.RAW_NATNET_TOPIC, layout.RAW_PILOT_TOPIC)


class ReplayOutput:
    """The output recording of one replay (module docstring).

    Parameters
    ----------
    path : str or Path
        ``DIR/replay.mcap``.
    log : str or Path
        The replayed recording.
    config : Config
        Settings of the replay (the signal's filter and threshold).
    window_ns : (int or None, int or None)
        Absolute log-time window replayed (``end`` exclusive).
    created_by : str
        The command, stored in the metadata record ``groundstation.replay``.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        log: str | os.PathLike[str],
        config: Config,
        window_ns: tuple[int | None, int | None] = (None, None),
        created_by: str = "groundstation replay",
    ) -> None:
        self.path, self.log, self.window_ns = Path(path), Path(log), window_ns
        with open_recording(log) as rec:
            meta, truth = rec.metadata(), rec.truth()
        self.recorder = Recorder(self.path, metadata=meta)
        self.recorder.add_metadata(
            "groundstation.replay", {"created_by": created_by, "source": str(log)}
        )
        if truth is not None:
            self.recorder.add_truth(truth)
        self.translator = FoxgloveTranslator(config.contact, config.alignment, keep_signal=True)
        self.fox = FoxgloveWriter(self.recorder, self.translator)
        self.samples = 0
        self._closed = False

    def sample(self, env: Envelope) -> None:
        """One decoded sample envelope of the replay (its Foxglove translations are written)."""
        self.samples += 1
        self.fox.add(env, env.header.recv_ns or None)

    def samples_from_log(self, acquisition=None) -> None:
        """Decode the log's samples here (a multi-process replay has no in-process tap)."""
        from groundstation.acquisition.replay import iter_replay

        with open_recording(self.log) as rec:
            t0 = rec.summary.start_ns or 0
        start, end = (None if t is None else (t - t0) / 1e9 for t in self.window_ns)
        for env in iter_replay(str(self.log), start, end, settings=acquisition):
            if env.topic.startswith("samples."):
                self.sample(env)

    def results(self, result) -> None:
        """The pipeline's results (a ``PipelineResult``): envelopes and their translations."""
        for env in result_envelopes(result):
            write_envelope(self.recorder, env)
            self.fox.add(env, env.header.source_ns)

    def close(self) -> dict:
        """Copy the raw channels, write the final Foxglove state, close; returns counts."""
        if self._closed:
            return {}
        self._closed = True
        copied = 0
        try:
            start, end = self.window_ns
            with open_recording(self.log) as rec:
                for msg in rec.messages(RAW_COPY, start, end):
                    copy_message(self.recorder, msg)
                    copied += 1
            self.fox.finish()
        finally:
            stats = self.recorder.close()
        return {
            "raw_copied": copied,
            "foxglove": dict(self.translator.counts),
            "foxglove_bad": self.translator.bad,
            "bytes": stats.bytes_written,
        }

    # -- for report.html -----------------------------------------------------------------------
    def signal(self) -> tuple[np.ndarray, np.ndarray]:
        """(t_ns (n,) int64, filtered |a| (n,) G) of the replayed samples."""
        series = self.translator.signal_series or []
        if not series:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        t, g = zip(*series, strict=True)
        return np.asarray(t, dtype=np.int64), np.asarray(g, dtype=np.float64)

    def trajectory(self) -> np.ndarray:
        """(m, 3) flown path, metres (thinned by distance)."""
        return self.translator.trajectory.points()
