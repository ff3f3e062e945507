"""``groundstation view`` argument handling (no bus needed for these)."""

from __future__ import annotations

import argparse

import pytest

from groundstation.cli import main
from groundstation.cli import view as view_cli
from groundstation.errors import ConfigError


def _args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    view_cli.add_view_arguments(p)
    return p.parse_args(list(argv))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "exactly one of --connect"),
        (["--connect", "tcp://127.0.0.1:1", "--session", "abc"], "exactly one of --connect"),
        (["--connect", " , "], "names no endpoint"),
        (["--connect", "tcp://127.0.0.1:1", "--std-range", "0.1"], "LO,HI"),
        (["--connect", "tcp://127.0.0.1:1", "--every", "0"], "--every"),
        (["--connect", "udp://127.0.0.1:1", "--headless"], "not tcp://"),
    ],
)
def test_bad_arguments_exit_2_with_a_message(argv, message, capsys, tmp_path):
    assert main(["view", *argv, "--out", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err


def test_session_endpoints_and_settings(tmp_path):
    from groundstation.runtime.session import Session

    Session("ab12", ("recorder",), str(tmp_path)).write_info()  # the session must exist
    args = _args("--session", "ab12", "--publishers", "mapper,mocap", "--std-range", "0,0.2",
                 "--trajectory-s", "5", "--show-internal",
                 "--session-root", str(tmp_path))  # fmt: skip
    eps = [e.replace(str(tmp_path), "/tmp") for e in view_cli._endpoints(args)]
    assert eps == [
        "ipc:///tmp/gs-ab12/mapper.sock", "ipc:///tmp/gs-ab12/mapper.sock.latest",
        "ipc:///tmp/gs-ab12/mocap.sock", "ipc:///tmp/gs-ab12/mocap.sock.latest",
    ]  # fmt: skip
    s = view_cli._settings(args)
    assert s.std_range == (0.0, 0.2) and s.trajectory_window_s == 5.0 and s.show_internal
    with pytest.raises(ConfigError):
        view_cli._settings(_args("--connect", "x", "--std-range", "0.2,0.1"))
