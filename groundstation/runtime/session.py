"""One acquisition session: where each process binds on the bus, and the acquisition settings.

Endpoint scheme
---------------
A session is a directory ``/tmp/gs-<session>/`` (``<session>`` is a short id; the ipc path limit
is 107 bytes). Every *publishing* process binds::

    ipc:///tmp/gs-<session>/<process>.sock          lossless topics (and the only socket when
                                                    a process publishes one policy)
    ipc:///tmp/gs-<session>/<process>.sock.latest   latest-value topics (status, link.health)
    ipc:///tmp/gs-<session>/<process>.flow          credit back channel (replay at speed=max)

and every subscriber connects its SUB sockets to the ``.sock`` / ``.sock.latest`` endpoints of
every publishing process of the session (:meth:`Session.subscribe_endpoints`). ZeroMQ retries an
ipc connect until the path is bound, so start order does not matter; publishers call
``Publisher.wait_for_subscribers`` (the XPUB ready handshake) on their data topics before sending
the first sample, so nothing is lost at start. The ``live`` and ``replay`` commands reuse this
module: they only add process names.

The session directory also holds ``session.json`` (the publishers, the supervisor's pid:
``groundstation view --session ID`` finds every publisher from it and fails fast when the
session does not exist) and ``config.toml``, the configuration resolved once by ``live``/``replay``
and read by every worker (:mod:`groundstation.runtime.configuration`).

Settings
--------
:class:`~groundstation.acquisition.settings.AcquisitionSettings` is the ``[acquisition]`` section
of ``groundstation.config.Config``; :func:`load_settings` loads (and so validates) the whole
configuration and returns it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import secrets
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Literal

from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.errors import ConfigError

#: Publishing processes of a live/record session, in start order.
LIVE_PUBLISHERS: tuple[str, ...] = ("link", "mocap", "recorder")
#: Publishing process of a replay session.
REPLAY_PUBLISHER = "replay"
_IPC_MAX = 107
INFO_FILE = "session.json"


def load_settings(
    path: str | Path | None = None, overrides: Sequence[str] = ()
) -> AcquisitionSettings:
    """Load :class:`AcquisitionSettings` from the ``[acquisition]`` table and ``acquisition.*``
    overrides; the other tables and overrides are checked by ``groundstation.config``.

    Raises
    ------
    ConfigError
        Unknown key, bad value, unreadable file.
    """
    from groundstation.config import load_config

    return load_config(path, overrides).acquisition


# -- endpoints -----------------------------------------------------------------------------------


def new_session_id() -> str:
    """A short random session id (8 hex digits)."""
    return secrets.token_hex(4)


@dataclasses.dataclass(frozen=True)
class Session:
    """Endpoints of one session (see the module docstring).

    Parameters
    ----------
    session_id : str
        Short id; the directory is ``<root>/gs-<session_id>``.
    publishers : tuple of str
        Names of the publishing processes subscribers connect to.
    root : str
        Parent directory of the session directory (default ``/tmp``).
    """

    session_id: str
    publishers: tuple[str, ...] = LIVE_PUBLISHERS
    root: str = "/tmp"

    def __post_init__(self) -> None:
        if not self.session_id or "/" in self.session_id:
            raise ConfigError(f"bad session id {self.session_id!r}: use letters and digits")
        longest = max(self.publishers, key=len, default="x")
        if len(self.endpoint(longest, "latest")) - len("ipc://") > _IPC_MAX:
            raise ConfigError(
                f"session directory {self.directory!r} is too long for ipc endpoints "
                f"(<= {_IPC_MAX} bytes)",
                hint="use a shorter --session root (e.g. /tmp)",
            )

    @property
    def directory(self) -> str:
        return os.path.join(self.root, f"gs-{self.session_id}")

    def ensure_directory(self) -> str:
        """Create the session directory (idempotent) and return it."""
        os.makedirs(self.directory, mode=0o700, exist_ok=True)
        return self.directory

    def cleanup(self) -> None:
        """Remove the session directory (after every process of the session has exited)."""
        import shutil

        shutil.rmtree(self.directory, ignore_errors=True)

    def write_info(self, **extra: object) -> str:
        """Write ``session.json`` (publishers, root, supervisor pid, extra keys); its path."""
        self.ensure_directory()
        path = os.path.join(self.directory, INFO_FILE)
        info = {"session": self.session_id, "publishers": list(self.publishers),
                "root": self.root, "pid": os.getpid(), **extra}  # fmt: skip
        tmp = path + ".tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(info, fh)
        os.replace(tmp, path)
        return path

    @classmethod
    def find(cls, session_id: str, root: str = "/tmp") -> Session:
        """The running session ``session_id`` under ``root``, from its ``session.json``.

        Raises
        ------
        ConfigError
            No such session (the message lists the sessions that exist under ``root``).
        """
        probe = cls(session_id, (), root)
        path = os.path.join(probe.directory, INFO_FILE)
        try:
            with open(path, encoding="utf-8") as fh:
                info = json.load(fh)
            pubs = tuple(str(p) for p in info["publishers"])
        except (OSError, ValueError, KeyError, TypeError):
            running = list_sessions(root)
            raise ConfigError(
                f"no session {session_id!r} under {root} (no {path})",
                hint=("running sessions: " + ", ".join(running))
                if running
                else "start one with 'groundstation live'; it prints its session id",
            ) from None
        return cls(session_id, pubs, root)

    def endpoint(self, process: str, policy: Literal["lossless", "latest"] = "lossless") -> str:
        """Bind endpoint of ``process`` for one drop policy."""
        base = f"ipc://{self.directory}/{process}.sock"
        return base if policy == "lossless" else base + ".latest"

    def flow_endpoint(self, process: str) -> str:
        """Credit back channel of ``process`` (only publishers with flow control bind it)."""
        return f"ipc://{self.directory}/{process}.flow"

    def subscribe_endpoints(self, exclude: Iterable[str] = ()) -> list[str]:
        """Every publisher endpoint of the session (both policies), minus ``exclude``."""
        skip = set(exclude)
        out: list[str] = []
        for name in self.publishers:
            if name not in skip:
                out += [self.endpoint(name), self.endpoint(name, "latest")]
        return out

    def publisher_kwargs(self, process: str) -> dict[str, str]:
        """``endpoint`` / ``latest_endpoint`` keyword arguments for ``Publisher``."""
        self.ensure_directory()
        return {
            "endpoint": self.endpoint(process),
            "latest_endpoint": self.endpoint(process, "latest"),
        }

    def as_args(self) -> list[str]:
        """Command-line arguments that rebuild this session in a worker process."""
        return [
            "--session", self.session_id, "--session-root", self.root,
            "--publishers", ",".join(self.publishers),
        ]  # fmt: skip


def list_sessions(root: str = "/tmp") -> list[str]:
    """Ids of the sessions under ``root`` that have a ``session.json``."""
    try:
        names = os.listdir(root)
    except OSError:
        return []
    return sorted(
        n[3:] for n in names
        if n.startswith("gs-") and os.path.exists(os.path.join(root, n, INFO_FILE))
    )  # fmt: skip


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """``--session``, ``--session-root``, ``--config`` and ``--set`` for a worker entry point."""
    parser.add_argument("--session", required=True, help="session id (see session.py)")
    parser.add_argument("--session-root", default="/tmp", help="parent of the session directory")
    parser.add_argument("--publishers", default=",".join(LIVE_PUBLISHERS),
                        help="comma-separated publishing processes of the session")  # fmt: skip
    parser.add_argument(
        "--config", default=None, help="TOML configuration file (default: the session's)"
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )


def worker_config(args: argparse.Namespace):
    """The configuration of a worker: the session's ``config.toml`` written by the command that
    started the session, or ``--config``/``--set`` for a worker started by hand."""
    from groundstation.runtime.configuration import worker_config as _load

    session = session_from_args(args)
    return _load(session.directory, args.config, args.set)


def session_from_args(args: argparse.Namespace) -> Session:
    """The :class:`Session` described by :func:`add_session_arguments` options."""
    pubs = tuple(p for p in args.publishers.split(",") if p)
    return Session(args.session, pubs, args.session_root)


# -- process shell helpers -----------------------------------------------------------------------


class StopSignals:
    """Turns SIGINT/SIGTERM into a flag the process loop checks (``bool(stop)``); ``event`` is
    the same flag as a :class:`threading.Event` for loops that wait on one."""

    def __init__(self) -> None:
        import signal
        import threading

        self.received: list[str] = []
        self.event = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, _frame: object) -> None:
        import signal

        self.set(signal.Signals(signum).name)

    def set(self, reason: str) -> None:
        """Ask for a stop (``reason`` is kept in :attr:`received`)."""
        self.received.append(reason)
        self.event.set()

    def __bool__(self) -> bool:
        return bool(self.received)


class RateCounter:
    """Messages per topic, and their rate since the previous :meth:`snapshot` (caller's clock)."""

    def __init__(self) -> None:
        self.total: dict[str, int] = {}
        self._last: dict[str, int] = {}
        self._last_ns: int | None = None

    def add(self, topic: str, n: int = 1) -> None:
        self.total[topic] = self.total.get(topic, 0) + n

    def snapshot(self, now_ns: int) -> dict[str, dict[str, float]]:
        """``{topic: {"count": n, "rate_hz": r}}`` with rates over the time since the last call."""
        dt = None if self._last_ns is None else (now_ns - self._last_ns) / 1e9
        out = {}
        for topic, n in sorted(self.total.items()):
            rate = (n - self._last.get(topic, 0)) / dt if dt else 0.0
            out[topic] = {"count": n, "rate_hz": round(rate, 2)}
        self._last, self._last_ns = dict(self.total), now_ns
        return out


def publish_log(pub, process: str, level: str, message: str, hint: str | None = None) -> None:
    """Put a warning/error on the ``log`` topic (never raises: logging must not kill a loop)."""
    try:
        pub.publish("log", {"process": process, "level": level, "message": message, "hint": hint})
    except Exception:  # noqa: BLE001 - a closed socket at shutdown
        pass
    import sys

    print(f"[{process}] {level}: {message}", file=sys.stderr, flush=True)
