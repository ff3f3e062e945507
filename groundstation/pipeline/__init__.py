"""The mapping pipeline on a recording: replay -> detector stage -> mapper -> outputs.

- :mod:`~groundstation.pipeline.offline`: in process, no sockets (fast, deterministic).
- :mod:`~groundstation.pipeline.multiprocess`: the same stages as real processes on a session
  bus under the supervisor (replay source, ``contact.process``, ``mapping.process``).
- :mod:`~groundstation.pipeline.scoring` (pure): metrics against the recording's truth.
- :mod:`~groundstation.pipeline.outputs`: mesh.ply, observations.csv, report.json, snapshots.

Settings: :func:`load_pipeline_config` returns the station :class:`~groundstation.config.Config`
with the two sections the pipeline reads beside it, ``mapper`` and ``alignment``, from one TOML
file and ``--set`` list (``groundstation config show`` prints them all).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from groundstation.config import Config, load_config
from groundstation.contact.settings import AlignmentSettings
from groundstation.mapping.settings import MapperSettings


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Everything the pipeline reads: the station config and its mapper/alignment sections."""

    config: Config
    mapper: MapperSettings
    alignment: AlignmentSettings


def load_pipeline_config(
    path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> PipelineConfig:
    """Load once at the entry point (``config.load_config``); raises ConfigError."""
    config = load_config(path, list(overrides))
    return PipelineConfig(config, config.mapper, config.alignment)
