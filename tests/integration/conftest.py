"""Fixtures shared by the integration tests (real ZeroMQ sockets, real session directories)."""

from __future__ import annotations

import glob
import shutil
import threading

import pytest
import zmq


@pytest.fixture(autouse=True)
def _remove_session_dirs():
    """Sessions bind ipc sockets under /tmp/gs-<id>/: remove the ones this test created."""
    before = set(glob.glob("/tmp/gs-*"))
    yield
    for d in set(glob.glob("/tmp/gs-*")) - before:
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
