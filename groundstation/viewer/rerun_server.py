"""Rerun's server for the web view: settings, the ``rerun --serve-web`` child process.

:class:`RerunServer` runs Rerun's own server (the CLI shipped in the ``rerun-sdk`` wheel) as a
child process: a gRPC proxy that buffers the stream for late viewers and an HTTP server for the
web viewer. It binds to ``127.0.0.1`` unless told otherwise (the Python SDK's own
``serve_grpc``/``serve_web_viewer`` bind every interface, which is why the CLI is used), dies with
its owner, and :attr:`RerunServer.web_url` is the page to open. A missing ``rerun-sdk`` raises
:class:`RerunUnavailable` (a ``GroundstationError`` with the install hint) before anything
starts.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.parse

from groundstation.errors import ConfigError, GroundstationError


class RerunUnavailable(GroundstationError, RuntimeError):
    """rerun-sdk is not installed, or its server did not start."""


def require_rerun():
    """Import ``rerun`` or raise :class:`RerunUnavailable` with the install hint."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise RerunUnavailable(
            f"--viewer rerun needs the rerun-sdk package ({exc})",
            hint="install it with ./bootstrap.sh (without GS_NO_RERUN=1) or "
            ".venv/bin/pip install -e '.[rerun]'",
        ) from None
    return rr


@dataclasses.dataclass(frozen=True)
class RerunSettings:
    """Where the web view is served and what the stream keeps.

    Attributes
    ----------
    bind : str
        Address both servers listen on; ``127.0.0.1`` (default) keeps them on this machine:
        reach them from elsewhere through an SSH tunnel (README). ``0.0.0.0`` exposes them to
        the network without authentication.
    web_port : int
        HTTP port of the web viewer page (Rerun's default 9090; 0 picks a free one).
    grpc_port : int
        gRPC port of the data stream (Rerun's default 9876; 0 picks a free one).
    server_memory_limit : str
        What the server buffers for late viewers (Rerun syntax: ``"1GiB"``, ``"25%"``).
    rrd : str or None
        Also save the stream to this ``.rrd`` file (opens with ``rerun FILE``).
    pose_rate_hz : float
        Vehicle transforms logged at most this often (data time).
    """

    bind: str = "127.0.0.1"
    web_port: int = 9090
    grpc_port: int = 9876
    server_memory_limit: str = "1GiB"
    rrd: str | None = None
    pose_rate_hz: float = 20.0

    def __post_init__(self) -> None:
        for name in ("web_port", "grpc_port"):
            port = getattr(self, name)
            if not (isinstance(port, int) and 0 <= port <= 65535):
                raise ConfigError(f"rerun {name} {port!r} must be a port number 0-65535")
        if self.web_port and self.web_port == self.grpc_port:
            raise ConfigError(f"the web and gRPC ports must differ (both {self.web_port})")
        try:
            socket.getaddrinfo(self.bind, None)
        except (socket.gaierror, UnicodeError):
            raise ConfigError(
                f"--web-bind {self.bind!r} is not an address of this machine",
                hint="use 127.0.0.1 (default), 0.0.0.0 or one interface's address",
            ) from None
        if not self.pose_rate_hz > 0:
            raise ConfigError(f"pose_rate_hz {self.pose_rate_hz} must be > 0")


def _die_with_parent() -> None:
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


class RerunServer:
    """Rerun's gRPC proxy + web viewer as a child process (module docstring).

    Parameters
    ----------
    settings : RerunSettings
    start_timeout_s : float
        How long to wait for both ports to listen.
    """

    def __init__(self, settings: RerunSettings, start_timeout_s: float = 30.0) -> None:
        require_rerun()
        self.settings = s = settings
        exe = shutil.which("rerun", path=os.path.dirname(sys.executable)) or shutil.which("rerun")
        if exe is None:
            raise RerunUnavailable("the rerun command of rerun-sdk was not found on PATH")
        self.host = "127.0.0.1" if s.bind in ("0.0.0.0", "::", "") else s.bind
        self.grpc_port = s.grpc_port or _free_port(s.bind)
        self.web_port = s.web_port or _free_port(s.bind)
        for port in (self.grpc_port, self.web_port):
            if _listening(self.host, port):
                raise RerunUnavailable(
                    f"port {port} on {self.host} is already in use",
                    hint="choose others with --web-port / --grpc-port (0 = any free port)",
                )
        argv = [
            exe, "--serve-web", "--bind", s.bind, "--port", str(self.grpc_port),
            "--web-viewer-port", str(self.web_port), "--server-memory-limit",
            s.server_memory_limit,
        ]  # fmt: skip
        env = dict(os.environ, RERUN_ANALYTICS="0", CI=os.environ.get("CI", "1"))
        # Same process group as this process (a supervisor that stops a worker's group stops
        # its server too), and SIGTERM when this process dies (Linux), so no orphan keeps the
        # ports.
        self.proc = subprocess.Popen(  # noqa: S603 - our own argv
            argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            env=env, preexec_fn=_die_with_parent,
        )  # fmt: skip
        deadline = time.monotonic() + start_timeout_s
        while not (_listening(self.host, self.grpc_port) and _listening(self.host, self.web_port)):
            if self.proc.poll() is not None:
                err = (self.proc.stderr.read() or b"").decode(errors="replace")[-400:]
                raise RerunUnavailable(f"rerun server exited ({self.proc.returncode}): {err}")
            if time.monotonic() > deadline:
                self.close()
                raise RerunUnavailable(f"rerun server did not listen within {start_timeout_s} s")
            time.sleep(0.1)

    @property
    def exposure_warning(self) -> str | None:
        """A warning to print when the servers listen beyond this machine (no authentication)."""
        import ipaddress

        try:
            loopback = ipaddress.ip_address(self.settings.bind).is_loopback
        except ValueError:
            loopback = self.settings.bind == "localhost"
        if loopback:
            return None
        return (
            f"WARNING: the web view listens on {self.settings.bind} (ports {self.web_port} and "
            f"{self.grpc_port}) with no authentication: anyone who can reach them sees the "
            "session (README, Web view: use an SSH tunnel instead)"
        )

    @property
    def grpc_url(self) -> str:
        """Where the SDK (and viewers) connect: ``rerun+http://HOST:PORT/proxy``."""
        return f"rerun+http://{self.host}:{self.grpc_port}/proxy"

    @property
    def web_url(self) -> str:
        """The web viewer page, already pointed at the stream."""
        url = urllib.parse.quote(self.grpc_url, safe="")
        return f"http://{self.host}:{self.web_port}/?url={url}"

    def close(self) -> None:
        """Stop the server (idempotent)."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        if self.proc.stderr is not None:
            self.proc.stderr.close()
