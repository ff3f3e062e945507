"""A session's configuration: resolved once, written to the session directory, read by workers.

``live``, ``record`` and ``replay`` resolve the configuration once at the entry point
(:func:`resolve`: defaults, an optional base, ``--config FILE``, ``--set key=value``) and write
the whole result to ``<session directory>/config.toml`` (:func:`write_session_config`). Every
worker of the session reads that file (:func:`worker_config`) instead of re-parsing flags, and
the recorder stores the same text, every section, in the recording's metadata, so a replay
starts from exactly the settings the session ran with.

Whatever replays a recording (``replay``, ``batch``, ``bench sessions --logs``, ``calibrate``,
``export foxglove``) uses the configuration recorded in it as its base
(:func:`resolve_for_recording`; a SITL recording holds its simulated airframe's ``[vehicle]``);
the user's ``--config`` and ``--set`` apply on top. Keys the running version does not know (a
recording from a newer or older version) are reported and skipped (:func:`known_tables`), never
fatal.
"""

from __future__ import annotations

import dataclasses
import sys
import tomllib
import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from groundstation.config import Config, load_config, to_toml
from groundstation.errors import ConfigError

CONFIG_FILE = "config.toml"


@dataclasses.dataclass(frozen=True)
class Resolved:
    """A configuration resolved once for a session.

    Attributes
    ----------
    config : Config
    text : str
        ``to_toml(config)``: what is written to the session directory and the recording.
    skipped : tuple of str
        Base keys this version does not know (dotted names), skipped.
    base : str
        Where the base came from ("defaults", or "the recording ...").
    """

    config: Config
    text: str
    skipped: tuple[str, ...] = ()
    base: str = "defaults"


def known_tables(tree: Mapping[str, Any], cls: type = Config, where: str = "") -> tuple[dict, list]:
    """Split a TOML tree into the keys :class:`Config` knows and the dotted names of the rest.

    Parameters
    ----------
    tree : mapping
        Parsed TOML (tables are dicts).
    cls : dataclass type
        The (section) class the tree should mirror.

    Returns
    -------
    clean : dict
        Known keys only (values unchecked: :func:`~groundstation.config.load_config` checks).
    skipped : list of str
        Unknown keys, and tables given where a value is expected (or the reverse).
    """
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls)}
    clean: dict[str, Any] = {}
    skipped: list[str] = []
    for key, value in tree.items():
        name = f"{where}{key}"
        if key not in fields:
            skipped.append(name)
            continue
        section = dataclasses.is_dataclass(hints[key])
        if section != isinstance(value, dict):
            skipped.append(name)
        elif section:
            sub, more = known_tables(value, hints[key], f"{name}.")
            clean[key] = sub
            skipped += more
        else:
            clean[key] = value
    return clean, skipped


def resolve(
    config_path: str | Path | None = None,
    overrides: Sequence[str] = (),
    base: Mapping[str, Any] | None = None,
    base_name: str = "defaults",
) -> Resolved:
    """The session's configuration: defaults, ``base`` (keys unknown to this version and values
    it rejects are skipped and listed in ``Resolved.skipped``), the file, the overrides (checked
    strictly: a typo in what the user types is an error).

    Raises
    ------
    ConfigError
        Bad file, unknown or bad ``--set`` key, bad value (also a bad known base value).
    """
    clean, skipped = known_tables(base or {})
    clean, bad = _valid_values(clean)
    config = load_config(config_path, list(overrides), base=clean)
    return Resolved(config, to_toml(config), tuple(skipped + bad), base_name)


def _valid_values(tree: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """Drop the base values this version rejects (e.g. a choice a newer version added), each
    reported as ``section.key (reason)``; a base never makes the resolution fail."""
    try:
        load_config(base=tree)
        return tree, []
    except ConfigError:
        pass
    good: dict[str, Any] = {}
    bad: list[str] = []
    for section, table in tree.items():
        for key, value in (table or {}).items():
            try:
                load_config(base={section: {key: value}})
            except ConfigError as exc:
                bad.append(f"{section}.{key} ({exc.message})")
                continue
            good.setdefault(section, {})[key] = value
    return good, bad


def recorded_base(meta: Mapping[str, str] | None) -> tuple[dict[str, Any], str]:
    """The configuration tree stored in a recording's ``groundstation`` metadata, and a
    description of it ("" when the recording holds none).

    Recordings made before the whole configuration was stored hold only ``[acquisition]``; an
    unreadable text is reported in the description and ignored.
    """
    text = (meta or {}).get("config", "")
    if not text.strip():
        return {}, ""
    try:
        tree = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return {}, f"its configuration is not valid TOML ({exc}); using defaults"
    sections = ", ".join(sorted(k for k, v in tree.items() if isinstance(v, dict)))
    return tree, f"the configuration recorded in the log ([{sections}])"


def recorded_text(log: str | Path) -> str:
    """The configuration text stored in a recording's (first segment's) ``groundstation``
    metadata; "" when it holds none or cannot be read as a recording (whoever replays it
    reports that error)."""
    import warnings

    from groundstation.acquisition.segments import open_session
    from groundstation.errors import GroundstationError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with open_session(log) as rec:
                return (rec.metadata() or {}).get("config", "")
    except (GroundstationError, OSError, ValueError):
        return ""


def resolve_for_recording(
    recorded: str, config_path: str | Path | None = None, overrides: Sequence[str] = ()
) -> Resolved:
    """:func:`resolve` on a recording's configuration text (:func:`recorded_text`) as the base;
    ``Resolved.base`` describes that base ("defaults" when the recording holds none)."""
    tree, what = recorded_base({"config": recorded})
    return resolve(config_path, overrides, base=tree, base_name=what or "defaults")


def settings_note(resolved: Resolved, on_top: bool) -> list[str]:
    """What a command replaying a recording says about its settings (one line each): where
    the base came from, and the recorded keys this version skipped."""
    more = " with --config/--set on top" if on_top else ""
    if resolved.base == "defaults":
        lines = [f"settings: defaults{more} (the log holds no configuration)"]
    else:
        lines = [f"settings: {resolved.base}{more}"]
    if resolved.skipped:
        lines.append(
            "recorded settings this version does not use, skipped: " + ", ".join(resolved.skipped)
        )
    return lines


def resolve_for_log(
    log: str | Path,
    config_path: str | Path | None,
    overrides: Sequence[str],
    command: str,
    quiet: bool = False,
) -> Resolved:
    """What a command replaying one recording runs with: the configuration recorded in
    ``log`` as the base, ``config_path`` and ``overrides`` on top; :func:`settings_note` on
    stderr as ``<command>: ...`` unless ``quiet``."""
    resolved = resolve_for_recording(recorded_text(log), config_path, overrides)
    if not quiet:
        for line in settings_note(resolved, bool(config_path or overrides)):
            print(f"{command}: {line}", file=sys.stderr, flush=True)
    return resolved


def recording_resolver(config_path: str | Path | None) -> Callable[[str, Sequence[str]], Config]:
    """``(recorded, overrides) -> Config`` for ``pipeline.batch.plan_batch``: each log's
    recorded configuration, then ``config_path``, then the overrides."""

    def resolve_one(recorded: str, overrides: Sequence[str]) -> Config:
        return resolve_for_recording(recorded, config_path, overrides).config

    return resolve_one


def recorded_note(
    recorded: Sequence[str], command: str, on_top: str = "--config/--set on top"
) -> list[str]:
    """What a command replaying many recordings says about their settings' bases: how many
    logs hold a recorded configuration (and which tables, ``on_top`` saying what applies over
    it), which hold an unreadable one, and recorded keys this version skipped."""
    texts = [t for t in recorded if t.strip()]
    if not texts:
        return []
    tables: set[str] = set()
    skipped: set[str] = set()
    broken = 0
    for text in texts:
        tree, what = recorded_base({"config": text})
        broken += not tree and "not valid TOML" in what
        tables.update(k for k, v in tree.items() if isinstance(v, dict))
        skipped.update(resolve_for_recording(text).skipped)
    used = len(texts) - broken
    rest = "; the rest from the defaults" if used < len(recorded) else ""
    lines = [
        f"{command}: {used} of {len(recorded)} logs start from the configuration recorded in "
        f"them ([{', '.join(sorted(tables))}]), {on_top}{rest}"
    ]
    if broken:
        lines.append(f"{command}: {broken} log(s) hold a configuration that is not valid TOML")
    if skipped:
        lines.append(
            f"{command}: recorded settings this version does not use, skipped: "
            + ", ".join(sorted(skipped))
        )
    return lines


def write_session_config(directory: str | Path, resolved: Resolved) -> Path:
    """Write ``config.toml`` into the session directory (atomically); returns its path."""
    path = Path(directory) / CONFIG_FILE
    tmp = path.with_suffix(".tmp")
    tmp.write_text(resolved.text, encoding="utf-8")
    tmp.replace(path)
    return path


def worker_config(
    directory: str | Path, config_path: str | None = None, overrides: Sequence[str] = ()
) -> Config:
    """A worker's configuration: ``--config`` / ``--set`` when given (a worker started by
    hand), else the session's ``config.toml``, else the defaults."""
    if config_path is not None or overrides:
        return load_config(config_path, list(overrides))
    path = Path(directory) / CONFIG_FILE
    return load_config(path if path.exists() else None)
