"""The mapping pipeline on a recording: replay -> detector stage -> mapper -> outputs.

- :mod:`~groundstation.pipeline.offline`: in process, no sockets (fast, deterministic).
- :mod:`~groundstation.pipeline.multiprocess`: the same stages as real processes on a session
  bus under the supervisor (replay source, ``contact.process``, ``mapping.process``).
- :mod:`~groundstation.pipeline.scoring` (pure): metrics against the recording's truth.
- :mod:`~groundstation.pipeline.outputs`: mesh.ply, observations.csv, report.json, snapshots.

Settings: :func:`load_pipeline_config` returns the station :class:`~groundstation.config.Config`
plus the two sections this pipeline adds, ``mapper`` (:class:`MapperSettings`) and
``alignment`` (:class:`AlignmentSettings`), read from the same TOML file and ``--set`` list.
While ``Config`` has no such sections, they are built here from the ``[mapper]`` /
``[alignment]`` tables and ``mapper.*`` / ``alignment.*`` overrides with the config module's
own coercion, so ``--set mapper.refit_period_s=4`` works either way.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from groundstation.config import Config, load_config
from groundstation.contact.stage import AlignmentSettings
from groundstation.errors import ConfigError
from groundstation.mapping.mapper import MapperSettings

_EXTRA = {"mapper": MapperSettings, "alignment": AlignmentSettings}


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Everything the pipeline reads: the station config and the mapper/alignment sections."""

    config: Config
    mapper: MapperSettings
    alignment: AlignmentSettings


def load_pipeline_config(
    path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> PipelineConfig:
    """Load once at the entry point (see the module docstring); raises ConfigError."""
    from groundstation import config as cfgmod

    own: dict[str, dict[str, Any]] = {k: {} for k in _EXTRA}
    rest: list[str] = []
    native = {f.name for f in dataclasses.fields(Config)}
    for item in overrides:
        key = item.partition("=")[0].strip()
        section = key.split(".", 1)[0]
        if section in _EXTRA and section not in native:
            value = item.partition("=")[2].strip()
            own[section][key.split(".", 1)[1] if "." in key else ""] = value
        else:
            rest.append(item)
    file_tables: dict[str, Any] = {}
    if path is not None and any(s not in native for s in _EXTRA):
        try:
            file_tables = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError):
            file_tables = {}  # load_config below reports the problem
    if file_tables and any(s in file_tables for s in _EXTRA if s not in native):
        # load_config would reject the extra tables: build from the tree without them
        stripped = {k: v for k, v in file_tables.items() if k not in _EXTRA or k in native}
        base = _load_dict(stripped, rest)
    else:
        base = load_config(path, rest)
    sections = {}
    for name, cls in _EXTRA.items():
        if name in native:
            sections[name] = getattr(base, name)
            continue
        data = dict(file_tables.get(name, {})) if isinstance(file_tables.get(name), dict) else {}
        for k, v in own[name].items():
            if not k:
                raise ConfigError(f"override {name!r} names a section, not a setting")
            data[k] = v
        sections[name] = cfgmod._build(cls, data, f"{name}.")  # noqa: SLF001 - same coercion
    return PipelineConfig(base, sections["mapper"], sections["alignment"])


def _load_dict(tree: dict[str, Any], overrides: list[str]) -> Config:
    from groundstation import config as cfgmod

    tree = {k: dict(v) if isinstance(v, dict) else v for k, v in tree.items()}
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"override {item!r} is not of the form section.key=value")
        cfgmod._set_path(tree, key.strip(), value.strip())  # noqa: SLF001
    return cfgmod._build(Config, tree, "")  # noqa: SLF001
