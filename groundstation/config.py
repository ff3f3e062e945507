"""Frozen configuration, loaded once at the entry point from TOML plus ``key=value`` overrides.

Each stage owns a frozen dataclass of its settings (defaults are the paper's); :class:`Config`
composes them. Nothing here reads files at import time. ``groundstation config show`` prints the
effective configuration as TOML so that every setting is visible.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.contact.settings import AlignmentSettings, ContactSettings
from groundstation.contact.vehicle import VehicleSettings
from groundstation.errors import ConfigError
from groundstation.mapping.settings import MapperSettings, MappingSettings, SurfaceSettings
from groundstation.pilot.settings import PilotSettings


@dataclasses.dataclass(frozen=True)
class Config:
    """The whole station's configuration; one section per stage."""

    acquisition: AcquisitionSettings = AcquisitionSettings()
    contact: ContactSettings = ContactSettings()
    vehicle: VehicleSettings = VehicleSettings()
    alignment: AlignmentSettings = AlignmentSettings()
    mapping: MappingSettings = MappingSettings()
    mapper: MapperSettings = MapperSettings()
    surface: SurfaceSettings = SurfaceSettings()
    pilot: PilotSettings = PilotSettings()


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    """Convert a TOML/CLI value to the dataclass field's annotated type, or raise ConfigError."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None or (isinstance(value, str) and value.lower() == "none"):
            if type(None) in args:
                return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: cannot use {value!r}: " + "; ".join(errors))
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.replace("(", "").replace(")", "").split(",") if v.strip()]
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        item = args[0] if args else Any
        return tuple(_coerce(v, item, where) for v in value)
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: {value!r} is not one of {list(args)}")
        return value
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on"):
            return True
        if isinstance(value, str) and value.lower() in ("false", "0", "no", "off"):
            return False
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if annotation is int:
        try:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
    if annotation is float:
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if annotation is str:
        return str(value)
    return value


def _build(cls: type, data: dict[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key not in fields:
            raise ConfigError(
                f"unknown setting {where}{key!r}",
                hint=f"known settings in this section: {', '.join(sorted(fields))}",
            )
        annotation = hints[key]
        if dataclasses.is_dataclass(annotation):
            if not isinstance(value, dict):
                raise ConfigError(f"{where}{key} is a section; give a table, not {value!r}")
            kwargs[key] = _build(annotation, value, f"{where}{key}.")
        else:
            kwargs[key] = _coerce(value, annotation, f"{where}{key}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"{where.rstrip('.') or 'config'}: {exc}") from exc


def _set_path(tree: dict[str, Any], dotted: str, value: str) -> None:
    parts = dotted.split(".")
    node = tree
    for part in parts[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"setting {dotted!r}: {part!r} is a value, not a section")
    node[parts[-1]] = value


def load_config(
    path: str | Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    base: dict[str, Any] | None = None,
) -> Config:
    """Load the configuration once: defaults, then ``base``, the TOML file, ``key=value``
    overrides.

    Parameters
    ----------
    path : path, optional
        TOML file whose tables mirror :class:`Config` (``[mapping]``, ``[surface]``, ...).
    overrides : list of str
        ``section.key=value`` strings, as given to ``--set`` on the command line.
    base : dict, optional
        Tables applied before the file (e.g. the configuration a recording was made with).
    """
    tree: dict[str, Any] = _merge({}, base or {})
    if path is not None:
        p = Path(path)
        try:
            tree = _merge(tree, tomllib.loads(p.read_text()))
        except FileNotFoundError:
            raise ConfigError(f"config file {str(p)!r} does not exist") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config file {str(p)!r} is not valid TOML: {exc}") from None
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {item!r} is not of the form section.key=value")
        _set_path(tree, key.strip(), value.strip())
    return _build(Config, tree, "")


def _merge(into: dict[str, Any], tree: dict[str, Any]) -> dict[str, Any]:
    """``into`` updated with ``tree``, tables merged key by key (copies, inputs untouched)."""
    out = dict(into)
    for key, value in tree.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        elif isinstance(value, dict):
            out[key] = _merge({}, value)
        else:
            out[key] = value
    return out


def to_toml(config: Any) -> str:
    """Render a (nested) frozen dataclass as TOML, for ``groundstation config show``."""

    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, tuple | list):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        if v is None:
            return '"none"'
        return repr(v)

    lines: list[str] = []

    def emit(obj: Any, prefix: str) -> None:
        scalars = [
            f for f in dataclasses.fields(obj) if not dataclasses.is_dataclass(getattr(obj, f.name))
        ]
        tables = [
            f for f in dataclasses.fields(obj) if dataclasses.is_dataclass(getattr(obj, f.name))
        ]
        if prefix and scalars:
            lines.append(f"[{prefix}]")
        for f in scalars:
            lines.append(f"{f.name} = {fmt(getattr(obj, f.name))}")
        if prefix and scalars:
            lines.append("")
        for f in tables:
            emit(getattr(obj, f.name), f"{prefix}.{f.name}" if prefix else f.name)

    emit(config, "")
    return "\n".join(lines).rstrip() + "\n"
