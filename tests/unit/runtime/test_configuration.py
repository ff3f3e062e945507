"""The configuration resolved once: the whole of it round-trips through the session file and
the recording; a recorded base with keys this version does not know is reported, not fatal."""

from __future__ import annotations

import tomllib

import pytest

from groundstation.config import Config, to_toml
from groundstation.errors import ConfigError
from groundstation.runtime.configuration import (
    known_tables,
    recorded_base,
    resolve,
    worker_config,
    write_session_config,
)


def test_the_whole_config_round_trips_through_toml():
    cfg = resolve(None, ["contact.threshold_g=0.9", "mapper.refit_period_s=3"]).config
    back = resolve(base=tomllib.loads(to_toml(cfg))).config
    assert back == cfg and back != Config()


def test_the_recorded_base_is_applied_under_the_users_settings_and_unknown_keys_skipped():
    base = tomllib.loads(to_toml(Config()))
    base["contact"]["threshold_g"] = 0.8
    base["mapper"]["from_the_future"] = 1
    base["future_section"] = {"x": 1}
    base["mapper"]["refit_period_s"] = "not a number"
    r = resolve(None, ["mapper.flag_u=0.25"], base=base)
    assert r.config.contact.threshold_g == 0.8 and r.config.mapper.flag_u == 0.25
    assert r.config.mapper.refit_period_s == Config().mapper.refit_period_s
    assert "mapper.from_the_future" in r.skipped and "future_section" in r.skipped
    assert any(s.startswith("mapper.refit_period_s") for s in r.skipped)
    with pytest.raises(ConfigError, match="unknown setting"):
        resolve(None, ["mapper.typo=1"], base=base)  # what the user types stays strict


def test_known_tables_and_recorded_base_of_old_and_broken_recordings():
    clean, skipped = known_tables({"acquisition": {"imu_rate_hz": 100}, "contact": 3})
    assert clean == {"acquisition": {"imu_rate_hz": 100}} and skipped == ["contact"]
    tree, what = recorded_base({"config": "[acquisition]\nimu_rate_hz = 100\n"})
    assert tree == {"acquisition": {"imu_rate_hz": 100}} and "[acquisition]" in what
    assert recorded_base({}) == ({}, "")
    tree, what = recorded_base({"config": "[[[ not toml"})
    assert tree == {} and "not valid TOML" in what


def test_workers_read_the_session_file_unless_given_flags(tmp_path):
    r = resolve(None, ["contact.threshold_g=0.7"])
    write_session_config(tmp_path, r)
    assert worker_config(tmp_path).contact.threshold_g == 0.7
    assert worker_config(tmp_path, None, ["contact.threshold_g=0.5"]).contact.threshold_g == 0.5
    assert worker_config(tmp_path / "none") == Config()


def test_a_batch_says_which_logs_start_from_their_recorded_configuration():
    from groundstation.runtime.configuration import recorded_note

    texts = ["", '[vehicle]\nshape = "guards"\n', "[contact]\nfrom_the_future = 1\n", "[[[ bad"]
    lines = recorded_note(texts, "batch")
    assert lines[0] == (
        "batch: 2 of 4 logs start from the configuration recorded in them ([contact, vehicle]), "
        "--config/--set on top; the rest from the defaults"
    )
    assert "1 log(s) hold a configuration that is not valid TOML" in lines[1]
    assert lines[2].endswith("skipped: contact.from_the_future")
    assert recorded_note(["", ""], "batch") == []
