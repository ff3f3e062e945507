"""Helpers for tests that run ``groundstation live`` against ``groundstation sitl`` as real
processes and inject faults into them (signals to workers, a stopped vehicle), then read what
the operator saw (status lines) and what was recorded.

Processes of a session are found from the kernel, not from what ``live`` says: every worker,
warm spare and fitting child carries ``GS_SUPERVISOR_PID`` (the ``live`` pid) in its
environment, and the active recorder is the holder of the session's ``recorder.lock``.
"""

from __future__ import annotations

import glob
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from tests.integration.test_pilot_sitl import free_udp_port, start, stop, wait_for

STATUS_RE = re.compile(r"^(?:!!!.*?!!!\s+)?t=\s*([0-9.]+) s")


def status_lines(path: Path) -> list[str]:
    """The status lines ``live`` printed so far (the ``final:`` line excluded)."""
    if not path.exists():
        return []
    return [ln for ln in path.read_text().splitlines() if STATUS_RE.match(ln)]


def session_processes(live_pid: int) -> dict[int, str]:
    """pid -> command line of every process whose environment names ``live_pid`` as its
    supervisor (workers, warm spares, fitting children)."""
    out = {}
    key = f"GS_SUPERVISOR_PID={live_pid}".encode()
    for env_path in glob.glob("/proc/[0-9]*/environ"):
        try:
            with open(env_path, "rb") as fh:
                env = fh.read().split(b"\0")
            if key not in env:
                continue
            pid = int(env_path.split("/")[2])
            with open(f"/proc/{pid}/cmdline", "rb") as fh:
                cmd = fh.read().replace(b"\0", b" ").decode(errors="replace")
            with open(f"/proc/{pid}/stat") as fh:
                if fh.read().rsplit(")", 1)[1].split()[0] == "Z":
                    continue  # a zombie is dead: only its parent has not reaped it yet
            out[pid] = cmd
        except (OSError, ValueError, IndexError):
            continue
    return out


def lock_holder(lock_path: str) -> int | None:
    """The pid holding an ``flock`` on ``lock_path`` (from /proc/locks), or None."""
    try:
        st = os.stat(lock_path)
    except OSError:
        return None
    dev_ino = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    with open("/proc/locks") as fh:
        for line in fh:
            parts = line.split()
            # "1: FLOCK  ADVISORY  WRITE 1234 08:01:5678 0 EOF" (blocked waiters have "->")
            if "->" in parts or "FLOCK" not in parts:
                continue
            k = parts.index("FLOCK")
            pid, ident = parts[k + 3], parts[k + 4]
            if ident.lower() == dev_ino.lower() or ident.endswith(f":{st.st_ino}"):
                return int(pid)
    return None


def private_root() -> str:
    """A short session root of our own: other test runs on the machine remove the ``/tmp/gs-*``
    folders that appear while they run (``conftest._remove_session_dirs``)."""
    return tempfile.mkdtemp(prefix="gsrt-", dir="/tmp")


@dataclass
class LiveRun:
    """A SITL and a ``live`` session started by :func:`start_session`."""

    tmp: Path
    sitl: subprocess.Popen
    live: subprocess.Popen
    session_dir: str
    root: str
    injections: list[tuple[str, float, int]] = field(default_factory=list)

    @property
    def out(self) -> Path:
        return self.tmp / "live.out"

    @property
    def err(self) -> Path:
        return self.tmp / "live.err"

    def lines(self) -> list[str]:
        return status_lines(self.out)

    def mark(self, what: str) -> int:
        """Note an injection now; returns the number of status lines printed before it."""
        n = len(self.lines())
        self.injections.append((what, time.monotonic(), n))
        return n

    def wait_lines(self, n: int, timeout: float | None = None) -> None:
        wait_for(lambda: self.live.poll() is not None or len(self.lines()) >= n,
                 timeout or n * 3 + 60, f"{n} status lines", poll=0.2)  # fmt: skip
        assert self.live.poll() is None, self.err.read_text()[-3000:]

    def shown(self, pattern: str, after: int, within: int = 3, timeout: float = 30) -> int:
        """Wait until one of the ``within`` status lines after line ``after`` matches
        ``pattern``; returns its index counted from ``after`` (1 = the first line after)."""
        rx = re.compile(pattern)

        def find() -> int | None:
            lines = self.lines()[after : after + within]
            for k, ln in enumerate(lines, 1):
                if rx.search(ln):
                    return k
            if len(self.lines()) >= after + within:
                raise AssertionError(
                    f"{pattern!r} not in the {within} status lines after the fault:\n"
                    + "\n".join(lines)
                )
            return None

        return wait_for(find, timeout, f"{pattern!r} on the status line", poll=0.2)

    def pid(self, name: str) -> int | None:
        """The running process of worker ``name`` (for ``recorder``: the one that writes, the
        holder of the lock), from what ``live`` printed when it (re)started it."""
        if name == "recorder":
            return lock_holder(os.path.join(self.session_dir, "recorder.lock"))
        pids = re.findall(rf"^started {name} \(pid (\d+)", self.err.read_text(), re.M)
        if not pids or not os.path.exists(f"/proc/{pids[-1]}"):
            return None
        return int(pids[-1])


def start_session(
    tmp: Path,
    sitl_args: list[str],
    live_args: list[str],
    *,
    record: bool = True,
) -> LiveRun:
    """SITL on a pty link path + UDP NatNet, ``live`` with the recording ``tmp/live.mcap``;
    returns once ``live`` has printed its session id."""
    mport = free_udp_port()
    root = private_root()
    link = tmp / "vehicle"
    sitl = start(
        ["sitl", "--link", f"pty:{link}", "--mocap", f"udp://127.0.0.1:{mport}",
         "--mocap-drop", "0", *sitl_args],
        tmp / "sitl.out", tmp / "sitl.err",
    )  # fmt: skip
    wait_for(lambda: link.is_symlink() or sitl.poll() is not None, 60, "the SITL link")
    rec = ["--record", str(tmp / "live.mcap")] if record else []
    live = start(
        ["live", "--link", f"serial://{link}?baud=921600",
         "--mocap", f"natnet://127.0.0.1:{mport}", "--summary", str(tmp / "summary.json"),
         "--session-root", root, *rec, *live_args],
        tmp / "live.out", tmp / "live.err",
    )  # fmt: skip

    def session() -> str | None:
        assert live.poll() is None, (tmp / "live.err").read_text()[-3000:]
        m = re.search(r"live: session (\w+)", (tmp / "live.err").read_text())
        return f"{root}/gs-{m.group(1)}" if m else None

    return LiveRun(tmp, sitl, live, wait_for(session, 60, "the session id", poll=0.1), root)


def finish(run: LiveRun, sig: int = signal.SIGINT) -> int:
    """Stop ``live`` (and the SITL); returns live's exit code."""
    try:
        rc = stop(run.live, sig, timeout=120)
    finally:
        stop(run.sitl, signal.SIGTERM)
        shutil.rmtree(run.root, ignore_errors=True)
    return rc
