"""The command-line shell: help, unknown commands, and errors printed without a traceback."""

from __future__ import annotations

from groundstation import cli


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
