"""Fixtures shared by the integration tests (real ZeroMQ sockets, real session directories)."""

from __future__ import annotations

import glob
import shutil
import threading

import pytest
import zmq


def _running(session_dir: str) -> bool:
    """A session whose ``session.json`` names a live process belongs to a running command
    (possibly another test run on this machine): leave it alone."""
    import json
    import os

    try:
        with open(os.path.join(session_dir, "session.json"), encoding="utf-8") as fh:
            os.kill(int(json.load(fh)["pid"]), 0)
        return True
    except (OSError, ValueError, KeyError, TypeError):
        return False


@pytest.fixture(autouse=True)
def _remove_session_dirs():
    """Sessions bind ipc sockets under /tmp/gs-<id>/: remove the ones this test created."""
    before = set(glob.glob("/tmp/gs-*"))
    yield
    for d in set(glob.glob("/tmp/gs-*")) - before:
        if not _running(d):
            shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def zctx():
    """A context torn down under a timeout: a socket left open fails the test, never hangs."""
    ctx = zmq.Context()
    yield ctx
    t = threading.Thread(target=ctx.term, daemon=True)
    t.start()
    t.join(10)
    if t.is_alive():
        ctx.destroy(linger=0)
        pytest.fail("ZeroMQ context leak: sockets still open at teardown")
