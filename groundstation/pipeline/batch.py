"""``groundstation batch``, the plan (pure): variants, logs, tasks, their keys and settings hash.

A batch replays every (log, variant) pair with ``pipeline.offline.run_offline`` and writes the
outputs of ``groundstation replay --out`` per pair. The batch is split by what each part needs:

- :mod:`.batch` (this module, pure): which tasks, under which settings, keyed how;
- :mod:`.pooling` (pure): pooled metrics of the task reports and the summary text;
- :mod:`.batch_outputs`: one task's folder on disk (run on a worker) and the summary files;
- ``groundstation.runtime.batch``: the Dask shell (cluster, submission, progress bar).

Task keys
---------
A task is identified by the log's content (sha256 of its bytes), the *resolved* settings and
the software that runs it: :func:`config_hash` hashes ``groundstation config show``'s TOML of
the effective :class:`~groundstation.config.Config`, the replay mode (``--map``, checkpoints)
and the software's identity (``runtime.batch.software_id``: its version and a digest of its
own files). Two variants that resolve to the same settings are one task; a renamed or copied
log is the same task; a changed default, or any change to the code, changes the key, so a
batch rerun after an upgrade replays again beside the old results instead of taking them for
its own. The task folder :attr:`Task.folder` carries both hashes.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable, Sequence
from pathlib import Path

from groundstation.config import Config, to_toml
from groundstation.errors import ConfigError

#: Name of the marker a finished task writes last (atomically) into its folder.
DONE = "done.json"
#: Written instead when the task failed (its error; the task reruns next time).
FAILED = "failed.json"

MAP_MODES = ("live", "final")


@dataclasses.dataclass(frozen=True)
class Variant:
    """A named list of ``--set`` overrides: ``NAME`` or ``NAME:key=value,key=value``.

    A value may itself hold commas (``surface.region_min=0,0,0``): a piece without ``=``
    continues the previous item.
    """

    name: str
    overrides: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str) -> Variant:
        name, _, rest = text.partition(":")
        name = name.strip()
        if not name:
            raise ConfigError(
                f"--variant {text!r}: give a name", hint="e.g. --variant low:contact.threshold_g=1"
            )
        items: list[str] = []
        for piece in rest.split(","):
            if "=" in piece or not items:
                items.append(piece.strip())
            else:
                items[-1] += "," + piece.strip()
        items = [s for s in items if s]
        for item in items:
            key, sep, _ = item.partition("=")
            if not sep or not key.strip():
                raise ConfigError(f"--variant {text!r}: {item!r} is not key=value")
        return cls(name, tuple(items))


@dataclasses.dataclass(frozen=True)
class LogInput:
    """One recording of a batch.

    Attributes
    ----------
    path : str
        Absolute path (workers of a remote cluster must see the same path).
    sha256 : str
        Hex digest of the file's bytes.
    overrides : tuple of str
        Settings this log needs before the batch's own (e.g. its airframe's ``[vehicle]``).
    labels : tuple of (str, str)
        Free tags carried into the summary (``engine``, ``role``, ``pair``...).
    recorded : str
        The configuration stored in the recording (TOML, "" if none): the base its settings are
        resolved on, as ``replay`` does (a live session's settings, a SITL flight's airframe).
    """

    path: str
    sha256: str
    overrides: tuple[str, ...] = ()
    labels: tuple[tuple[str, str], ...] = ()
    recorded: str = ""

    @property
    def name(self) -> str:
        return Path(self.path).stem

    def label(self, key: str, default: str = "") -> str:
        return dict(self.labels).get(key, default)


@dataclasses.dataclass(frozen=True)
class Task:
    """One replay: a log under resolved settings (what a worker runs)."""

    log: str
    log_sha256: str
    config: Config
    config_hash: str
    map_mode: str = "live"
    checkpoints: int | None = None
    software: str = ""

    @property
    def key(self) -> str:
        """``<log sha256>-<config hash>`` (hex): the identity of the result."""
        return f"{self.log_sha256}-{self.config_hash}"

    @property
    def folder(self) -> str:
        """``<log stem>-<log sha256[:12]>-<config hash[:12]>``."""
        stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(self.log).stem)
        return f"{stem[:60]}-{self.log_sha256[:12]}-{self.config_hash[:12]}"


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (variant, log) pair of the plan and the task that answers it."""

    variant: str
    log: LogInput
    task: Task


@dataclasses.dataclass(frozen=True)
class Plan:
    """Every cell of a batch and its distinct tasks (in first-use order)."""

    cells: tuple[Cell, ...]
    variants: tuple[Variant, ...]
    base_overrides: tuple[str, ...] = ()

    @property
    def tasks(self) -> tuple[Task, ...]:
        seen: dict[str, Task] = {}
        for c in self.cells:
            seen.setdefault(c.task.folder, c.task)
        return tuple(seen.values())


def replay_settings_text(
    config: Config, map_mode: str, checkpoints: int | None, software: str = ""
) -> str:
    """The resolved settings of a task as TOML: the config, the replay mode (checkpoints
    ``"growth"``: ``replay --map final`` without ``--checkpoints``) and the software that
    replays it (when given)."""
    cp = "'growth'" if checkpoints is None else str(int(checkpoints))
    text = to_toml(config) + f"\n[replay]\nmap = {map_mode!r}\ncheckpoints = {cp}\n"
    if software:
        text += f"\n[software]\ngroundstation = {software!r}\n"
    return text


def config_hash(
    config: Config, map_mode: str = "live", checkpoints: int | None = None, software: str = ""
) -> str:
    """sha256 (hex) of :func:`replay_settings_text`."""
    text = replay_settings_text(config, map_mode, checkpoints, software)
    return hashlib.sha256(text.encode()).hexdigest()


def plan_batch(
    logs: Sequence[LogInput],
    variants: Sequence[Variant],
    resolve: Callable[[str, Sequence[str]], Config],
    *,
    base_overrides: Sequence[str] = (),
    map_mode: str = "live",
    checkpoints: int | None = None,
    software: str = "",
) -> Plan:
    """Every (variant, log) cell with its task.

    Parameters
    ----------
    logs : sequence of LogInput
    variants : sequence of Variant
        Names must be unique; none means one variant ``default``.
    resolve : callable
        ``(recorded, overrides) -> Config``: the log's recorded configuration text
        (:attr:`LogInput.recorded`) as the base, the ``--config`` file and ``overrides`` on
        top (``runtime.configuration.resolve_for_recording``); raises ``ConfigError`` on a bad
        setting, before any work.
    base_overrides : sequence of str
        ``--set`` items of the batch; a log's own overrides come first, the variant's last.
    software : str
        The identity of the software that will run the tasks (``runtime.batch.software_id``),
        part of every task's key.
    """
    if map_mode not in MAP_MODES:
        raise ConfigError(f"--map {map_mode!r}: use live or final")
    if checkpoints is not None and checkpoints < 0:
        raise ConfigError(f"checkpoints must be >= 0, got {checkpoints}")
    variants = tuple(variants) or (Variant("default"),)
    names = [v.name for v in variants]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"--variant names must be unique: {', '.join(dup)} given twice")
    if not logs:
        raise ConfigError("a batch needs at least one log")
    cells: list[Cell] = []
    cache: dict[tuple[str, tuple[str, ...]], tuple[Config, str]] = {}
    for v in variants:
        for log in logs:
            key = (log.recorded, (*log.overrides, *base_overrides, *v.overrides))
            if key not in cache:
                cfg = resolve(log.recorded, list(key[1]))
                cache[key] = (cfg, config_hash(cfg, map_mode, checkpoints, software))
            cfg, h = cache[key]
            task = Task(log.path, log.sha256, cfg, h, map_mode, checkpoints, software)
            cells.append(Cell(v.name, log, task))
    return Plan(tuple(cells), variants, tuple(base_overrides))
