"""Open formats beside our own: Foxglove well-known schemas (protobuf) for every recording.

- :mod:`~groundstation.openformats.channels`: the table of Foxglove channels a recording carries
  (topic, schema, what it holds) and the MCAP schema registration data.
- :mod:`~groundstation.openformats.signal`: the detector's signal (filtered |a| in G) computed
  from IMU and attitude samples, as the detector computes it (pure).
- :mod:`~groundstation.openformats.state`: contacts with their trusted / flagged / pending
  state and the flown trajectory, kept for display (pure; shared with the Rerun sink).
- :mod:`~groundstation.openformats.foxglove`: bus envelopes -> Foxglove protobuf messages (pure).
- :mod:`~groundstation.openformats.export`: ``groundstation export foxglove`` and the replay
  output recording (file I/O around the translator).
"""
