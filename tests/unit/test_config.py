"""Configuration loading: defaults, TOML, overrides, and errors that name the bad setting."""

from __future__ import annotations

import pytest

from groundstation.config import Config, load_config, to_toml
from groundstation.errors import ConfigError


def test_defaults_are_the_papers():
    cfg = load_config()
    assert cfg.mapping.lengthscale == 0.25
    assert cfg.mapping.alpha == 2.0 and cfg.mapping.beta == 4.0
    # the map's prior mean leans unknown space outside on purpose (MappingSettings.prior_mean);
    # the paper's own protocol, reproduced by bench paper2d, keeps the paper's 0
    assert cfg.mapping.prior_mean == 0.3
    from groundstation.bench.paper2d import BenchSettings

    assert BenchSettings().prior_mean == 0.0
    assert cfg.surface.spacing == 0.05


def test_toml_then_overrides(tmp_path):
    path = tmp_path / "gs.toml"
    path.write_text('[mapping]\nlengthscale = 0.4\nmodel = "gpis"\n[surface]\nspacing = 0.1\n')
    cfg = load_config(
        path, ["mapping.lengthscale=0.3", "surface.region_min=0,0,0", "surface.region_max=9,5,3"]
    )
    assert cfg.mapping.lengthscale == 0.3
    assert cfg.mapping.model == "gpis"
    assert cfg.surface.spacing == 0.1
    assert cfg.surface.region_max == (9.0, 5.0, 3.0)


@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ("mapping.lengthscal=0.3", "lengthscal"),
        ("mapping.lengthscale=abc", "lengthscale"),
        ("mapping.lengthscale=-1", "lengthscale"),
        ("mapping.model=magic", "magic"),
        ("mapping.optimize=perhaps", "optimize"),
        ("nosuchsection.x=1", "nosuchsection"),
        ("justtext", "section.key=value"),
    ],
)
def test_bad_settings_name_the_problem(override, needle):
    with pytest.raises(ConfigError, match=needle):
        load_config(None, [override])


def test_a_value_a_section_refuses_names_the_section_once():
    with pytest.raises(ConfigError) as err:
        load_config(None, ["contact.external_max_tilt_deg=0"])
    assert str(err.value).startswith("contact: contact.external_max_tilt_deg must be in (0, 180]")


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[mapping\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_show_round_trips(tmp_path):
    cfg = load_config(None, ["mapping.beta=0.5"])
    path = tmp_path / "shown.toml"
    path.write_text(to_toml(cfg))
    assert load_config(path) == cfg
    assert isinstance(cfg, Config)
