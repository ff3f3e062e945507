"""Every command that writes a recording (or a tlog) refuses an existing file without
``--force`` (error naming it, exit 2, file untouched), and ``replay`` starts from the
configuration recorded with the log (saying so), the user's settings on top."""

from __future__ import annotations

import pytest

from groundstation.acquisition import layout
from groundstation.acquisition.recorder import Recorder
from groundstation.cli import main


@pytest.fixture
def existing(tmp_path):
    path = tmp_path / "exists.mcap"
    path.write_bytes(b"precious")
    return path


@pytest.mark.parametrize(
    "argv",
    [
        ["live", "--link", "serial:///dev/null", "--record", "{out}"],
        ["record", "--link", "serial:///dev/null", "--out", "{out}"],
        ["sitl", "--speed", "max", "--duration", "1", "--record", "{out}"],
        ["import", "csv", "nothing.csv", "--out", "{out}"],
        ["import", "ulog", "nothing.ulg", "--out", "{out}"],
        ["import", "tlog", "nothing.tlog", "--out", "{out}"],
        ["export", "tlog", "nothing.mcap", "--out", "{out}"],
    ],
)
def test_an_existing_output_is_never_overwritten_without_force(argv, existing, capsys, tmp_path):
    for name in ("nothing.csv", "nothing.ulg", "nothing.tlog", "nothing.mcap"):
        (tmp_path / name).write_bytes(b"input")
    argv = [str(tmp_path / a) if a.startswith("nothing.") else a for a in argv]
    rc = main([a.replace("{out}", str(existing)) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "already exists" in err and str(existing) in err and "--force" in err
    assert existing.read_bytes() == b"precious"


def test_force_replaces_a_sitl_recording(existing, capsys):
    argv = ["sitl", "--speed", "max", "--duration", "1", "--pilot", "script:hover",
            "--record", str(existing), "--force"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr().err
    assert existing.read_bytes()[:8] == b"\x89MCAP0\r\n"


def test_replay_starts_from_the_recorded_configuration(tmp_path, capsys):
    import argparse

    from groundstation.cli.replay import _resolve

    log = tmp_path / "log.mcap"
    config = "[contact]\nthreshold_g = 2.5\nfrom_a_newer_version = 1\n[mapper]\nflag_u = 0.4\n"
    meta = layout.station_metadata(station_version="t", created_by="pytest", config=config)
    with Recorder(log, metadata=meta):
        pass
    args = argparse.Namespace(config=None, set=["mapper.flag_u=0.2"], quiet=False)
    cfg = _resolve(log, args).config
    err = capsys.readouterr().err
    assert cfg.contact.threshold_g == 2.5 and cfg.mapper.flag_u == 0.2
    assert "the configuration recorded in the log ([contact, mapper])" in err
    assert "with --config/--set on top" in err
    assert "contact.from_a_newer_version" in err and "skipped" in err
