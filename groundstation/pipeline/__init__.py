"""The mapping pipeline on a recording: replay -> detector stage -> mapper -> outputs.

- :mod:`~groundstation.pipeline.offline`: in process, no sockets (fast, deterministic).
- :mod:`~groundstation.pipeline.multiprocess`: the same stages as real processes on a session
  bus under the supervisor (``runtime.workers``: replay source, detector, mapper).
- :mod:`~groundstation.pipeline.scoring` (pure): metrics against the recording's truth.
- :mod:`~groundstation.pipeline.outputs`: mesh.ply, observations.csv, report.json, snapshots.

Settings: the station :class:`~groundstation.config.Config` (``config.load_config``, one TOML
file and ``--set`` list); the pipeline reads its ``contact``, ``alignment``, ``mapping``,
``mapper``, ``surface`` and ``acquisition`` sections (``groundstation config show`` prints them).
"""
