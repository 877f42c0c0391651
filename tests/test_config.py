"""Team configs: a typo or an impossible value is a clear :class:`ConfigError`, never a silent
default or a crash later in the filter."""

from __future__ import annotations

from pathlib import Path

import pytest

from relloc.config import ConfigError, FilterConfig, LikelihoodConfig, TeamConfig

ROBOTS = """
[[robots]]
name = "a"
uwb_node = "n_1"
[[robots]]
name = "b"
uwb_node = "n_2"
"""


def _load(tmp_path: Path, extra: str) -> TeamConfig:
    path = tmp_path / "team.toml"
    path.write_text('reference = "a"\n' + extra + "\n" + ROBOTS)
    return TeamConfig.load(path)


def test_the_minimal_team_loads(tmp_path: Path) -> None:
    config = _load(tmp_path, "")
    assert config.robot_names == ("a", "b") and config.filter == FilterConfig()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ('[filter.likelihood]\nrange_model = "nlso"', "filter.likelihood.range_model: expected one of"),
        ('[filter.self_calibration]\nheading_mode = "estimated"', "heading_mode: expected one of"),
        ('[filter.self_calibration]\nbias_mode = "Online"', "bias_mode: expected one of"),
        ('[filter]\nspread_rotations = "false"', "spread_rotations: expected true or false"),
        ("[filter]\nparticles = 500.5", "particles: expected an integer"),
        ("[filter]\nparticles = 0", "particles must be >= 1"),
        ("[filter]\nupdate_period = -1.0", "update_period must be > 0"),
        ("[filter.likelihood]\nlos_sigma = nan", "los_sigma: expected a finite number"),
        ("[filter.likelihood]\nnlos_fraction = 0.99\ngross_fraction = 0.05", "nlos_fraction + gross_fraction"),
        ("[filter.resampling]\ness_threshold = 5.0", "filter.resampling.ess_threshold must be in [0, 1]"),
        ("[filter.likelihood]\nparticles = 10", "filter.likelihood: unknown key"),
        ("[filter]\nlikelihood = 3", "filter.likelihood must be a table"),
        ('[uwb.pairs.n_1-n_2]\nbias = 0.3\nscale = 0.0', "range scale must be > 0"),
        ('[uwb.pairs.n_1-n_2]\nbias = 0.3\nsigma = "x"', "sigma: expected a finite number"),
        ("area = [-inf, inf, -1.0, 1.0]", "area must be"),
        ("[uwb]\ndefault_bias = inf", "default_bias: expected a finite number"),
        ("uwb = 3", "malformed config"),
        ('[[robots]]\nname = "c"\nodom_mode = "wheels"', "odom_mode: expected one of"),
    ],
)
def test_bad_values_are_config_errors(tmp_path: Path, extra: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("+", r"\+")):
        _load(tmp_path, extra)


def test_a_folder_is_not_a_config(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        TeamConfig.load(tmp_path)


def test_configs_made_in_code_are_checked_too() -> None:
    """A config made in code (``FilterConfig(...)``, ``with_filter``, ``with_modes``) goes
    through the same checks as one read from a file."""
    with pytest.raises(ConfigError, match="range_model: expected one of"):
        LikelihoodConfig(range_model="nlso")  # type: ignore[arg-type]
    config = TeamConfig.from_dict({"reference": "a", "robots": [{"name": "a"}, {"name": "b"}]})
    with pytest.raises(ConfigError, match="spread_rotations: expected true or false"):
        config.with_filter(spread_rotations="false")
    with pytest.raises(ConfigError, match="heading_mode: expected one of"):
        config.with_modes(heading="magnetometer")


@pytest.mark.parametrize(
    ("key", "section"),
    [("los_sigma = 0.1", "likelihood"), ("process_noise = 0.01", "odometry"), ("resample = \"ess\"", "resampling"),
     ("heading_mode = \"estimate\"", "self_calibration"), ("selfcal_particles = 10", "self_calibration"),
     ("d_th = 0.2", "association")],
)
def test_an_old_flat_filter_key_names_its_new_place(tmp_path: Path, key: str, section: str) -> None:
    name = key.split(" ")[0]
    with pytest.raises(ConfigError, match=rf"filter\.{name} has moved to the \[filter\.{section}\] table"):
        _load(tmp_path, f"[filter]\n{key}")


def test_the_filter_sections_round_trip_and_take_changes_by_name(tmp_path: Path) -> None:
    config = _load(tmp_path, "[filter]\nparticles = 700\n[filter.likelihood]\nlos_sigma = 0.12\n"
                             "[filter.self_calibration]\nbias_mode = \"online\"")
    fc = config.filter
    assert (fc.particles, fc.likelihood.los_sigma, fc.self_calibration.bias_mode) == (700, 0.12, "online")
    assert TeamConfig.from_dict(config.to_dict()) == config
    assert "[filter.likelihood]" in config.to_toml()
    changed = config.with_filter(particles=5, selfcal_particles=7, d_th=0.3)
    assert (changed.filter.particles, changed.filter.self_calibration.selfcal_particles) == (5, 7)
    assert changed.filter.association.d_th == 0.3 and changed.filter.likelihood == fc.likelihood
    assert FilterConfig.choices("heading_mode") == ("compass", "estimate")
    with pytest.raises(TypeError, match="no field 'particle'"):
        config.with_filter(particle=5)
