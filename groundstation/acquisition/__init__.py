"""Acquisition: sources by URI, the MCAP recorder, the recording reader and importers.

- :mod:`groundstation.acquisition.layout`: the MCAP file-format contract (pure).
- :mod:`groundstation.acquisition.recorder`: :class:`~groundstation.acquisition.recorder.Recorder`,
  the writer around ``mcap.writer.Writer`` with bounded chunks and reported I/O errors.
- :mod:`groundstation.acquisition.reader`: :func:`~groundstation.acquisition.reader.open_recording`,
  time-ordered reading with seeking, and recovery of files truncated by a crash.
- :mod:`groundstation.acquisition.importers`: outside recordings (CSV IMU, PX4 ULog, MAVLink tlog)
  re-encoded as the wire bytes a live session would have recorded; an exporter to tlog.

Nothing is imported here, so ``import groundstation.acquisition`` stays cheap.
"""
