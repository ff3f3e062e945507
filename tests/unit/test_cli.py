"""The command-line shell: help, unknown commands, and errors printed without a traceback."""

from __future__ import annotations

import pytest

from groundstation import cli
from groundstation.errors import ConfigError


def test_top_level_help_lists_every_command(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for path in cli.COMMANDS:
        assert " ".join(path) in out


def test_unknown_command_is_an_error(capsys):
    assert cli.main(["fly-to-the-moon"]) == 2
    assert "unknown command" in capsys.readouterr().err


def test_group_without_subcommand_lists_choices(capsys):
    assert cli.main(["bench"]) == 2
    assert "paper2d" in capsys.readouterr().err


def test_every_registered_module_imports_and_builds_its_parser():
    import argparse

    for path in cli.COMMANDS:
        add_arguments, run = cli.load(path)
        parser = argparse.ArgumentParser(prog=" ".join(path))
        add_arguments(parser)
        assert callable(run)


def test_config_error_is_reported_not_raised(capsys):
    assert cli.main(["config", "show", "--set", "mapping.lengthscale=-2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "lengthscale" in err


def test_config_show_prints_toml(capsys):
    assert cli.main(["config", "show"]) == 0
    out = capsys.readouterr().out
    assert "[mapping]" in out and "lengthscale = 0.25" in out


def test_bad_link_uris_are_errors_without_a_traceback(capsys, tmp_path):
    """A bad link scheme printed a traceback (issue 14): firmware_bridge's UriError is not a
    GroundstationError, so the command line did not catch it."""
    for argv in (
        ["live", "--link", "foo://x", "--no-viewer", "--no-mapping", "--duration", "1"],
        ["live", "--link", "udp://127.0.0.1:14550", "--mocap", "bogus:nothing", "--no-viewer"],
        ["record", "--link", "foo://x", "--out", str(tmp_path / "x.mcap"), "--duration", "1"],
    ):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error:") and "hint:" in err and "Traceback" not in err, err


def test_live_signing_key_errors_name_the_file(capsys, tmp_path):
    bad = tmp_path / "short.key"
    bad.write_bytes(b"0123")
    for key, words in ((bad, "32 raw bytes or 64 hex"), (tmp_path / "missing.key", "cannot read")):
        argv = ["live", "--link", "udp://127.0.0.1:14550", "--signing-key", str(key)]
        assert cli.main([*argv, "--no-viewer", "--duration", "1"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error:") and words in err and str(key) in err, err


def test_live_signing_key_reaches_the_link_process_as_a_setting(tmp_path):
    """``--signing-key`` becomes ``acquisition.signing_key_file`` of the session's resolved
    configuration, which every worker (the link included) reads from the session directory."""
    import argparse

    from groundstation.cli.live import _check_signing, _signing_sets, add_live_arguments
    from groundstation.runtime.configuration import resolve

    key = tmp_path / "k.hex"
    key.write_text("ab" * 32)
    parser = argparse.ArgumentParser()
    add_live_arguments(parser)
    args = parser.parse_args(["--link", "udp://127.0.0.1:14550", "--signing-key", str(key)])
    resolved = resolve(args.config, [*args.set, *_signing_sets(args)])
    _check_signing(resolved)  # a readable key
    assert resolved.config.acquisition.signing_key_file == str(key.resolve())
    assert f'signing_key_file = "{key.resolve()}"' in resolved.text  # what the workers read
    key.write_text("not a key")
    with pytest.raises(ConfigError):
        _check_signing(resolve(args.config, [*args.set, *_signing_sets(args)]))
