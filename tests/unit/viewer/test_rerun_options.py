"""``--viewer rerun`` plumbing without starting anything: options, defaults, and what ``live``
hands its viewer worker (the web view binds to loopback unless told otherwise)."""

from __future__ import annotations

import argparse

import pytest

from groundstation.cli.live import add_live_arguments, plan
from groundstation.errors import ConfigError
from groundstation.viewer.rerun_sink import RerunSettings


def _live(*extra: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_live_arguments(p)
    return p.parse_args(["--link", "udp://127.0.0.1:14550", *extra])


def test_defaults_bind_to_loopback_on_rerun_ports():
    s = RerunSettings()
    assert (s.bind, s.web_port, s.grpc_port) == ("127.0.0.1", 9090, 9876)


@pytest.mark.parametrize(
    "kw", [{"web_port": 70000}, {"web_port": 9000, "grpc_port": 9000}, {"bind": "no such host!"}]
)
def test_bad_web_settings_are_config_errors(kw):
    with pytest.raises(ConfigError):
        RerunSettings(**kw)


def test_live_passes_the_web_options_to_its_viewer_worker():
    _, specs = plan(_live("--viewer", "rerun", "--web-port", "0", "--rrd", "x.rrd",
                          "--set", "contact.threshold_g=1.5"), "abcd1234")  # fmt: skip
    (viewer,) = [s for s in specs if s.name == "viewer"]
    argv = list(viewer.argv)
    i = argv.index("--viewer")
    assert argv[i + 1] == "rerun"
    assert argv[argv.index("--web-bind") + 1] == "127.0.0.1"
    assert argv[argv.index("--web-port") + 1] == "0"
    assert argv[argv.index("--rrd") + 1] == "x.rrd"
    # the signal plot uses the session's settings: the resolved config.toml of the session
    assert argv[argv.index("--config") + 1].endswith("config.toml")
    _, specs = plan(_live(), "abcd1234")
    (viewer,) = [s for s in specs if s.name == "viewer"]
    assert "--viewer" not in viewer.argv  # the Open3D window stays the default


def test_view_and_replay_accept_the_viewer_options():
    from groundstation.cli import load

    cases = (
        (("view",), ["--session", "abcd", "--viewer", "rerun"]),
        (("replay",), ["x.mcap", "--viewer", "rerun", "--serve-s", "5"]),
    )
    for path, argv in cases:
        add, _ = load(path)
        p = argparse.ArgumentParser()
        add(p)
        args = p.parse_args([*argv, "--web-bind", "0.0.0.0", "--grpc-port", "0"])
        assert (args.viewer, args.web_bind, args.grpc_port) == ("rerun", "0.0.0.0", 0)


@pytest.mark.parametrize(("bind", "warned"), [("127.0.0.1", False), ("::1", False),
                                              ("localhost", False), ("0.0.0.0", True)])  # fmt: skip
def test_listening_beyond_loopback_is_warned_about(bind, warned):
    from groundstation.viewer.rerun_server import RerunServer

    server = RerunServer.__new__(RerunServer)  # the property only: no process started
    server.settings, server.web_port, server.grpc_port = RerunSettings(bind=bind), 9090, 9876
    assert (server.exposure_warning is not None) == warned
