"""Shared test settings.

External recordings (``../shared/external_data``) are found through one setting: the
environment variable ``GS_EXTERNAL_DATA``, defaulting to ``../shared/external_data`` beside the
project root. Tests that need them use the ``external_data`` fixture and skip with a message
naming the missing path.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
EXTERNAL_DATA = Path(
    os.environ.get("GS_EXTERNAL_DATA", PROJECT_ROOT.parent / "shared" / "external_data")
)


@pytest.fixture(scope="session")
def external_data() -> Path:
    """Root of the external recordings; skips the test when it is absent."""
    if not EXTERNAL_DATA.is_dir():
        pytest.skip(
            f"external data not found at {EXTERNAL_DATA} "
            "(set GS_EXTERNAL_DATA to the folder holding natnet_capture/, aggressive_flight/, "
            "px4_ulog/)"
        )
    return EXTERNAL_DATA


@pytest.fixture(scope="session")
def bundled_replay():
    """``get(name)``: the in-process replay of ``replay_logs/<name>.mcap`` with the default
    settings (live refit cadence), run once per session. It is deterministic, and the pipeline
    and ``--map final`` tests both compare against it (each bundled log took 5-20 s per run).
    Callers must not modify the result."""
    from groundstation.config import load_config
    from groundstation.pipeline.offline import run_offline

    runs: dict = {}

    def get(name: str):
        if name not in runs:
            log = PROJECT_ROOT / "replay_logs" / f"{name}.mcap"
            runs[name] = run_offline(str(log), load_config())
        return runs[name]

    return get
