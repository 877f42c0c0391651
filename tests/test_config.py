"""Team configs: a typo or an impossible value is a clear :class:`ConfigError`, never a silent
default or a crash later in the filter."""

from __future__ import annotations

from pathlib import Path

import pytest

from relloc.config import ConfigError, FilterConfig, TeamConfig

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
        ('[filter]\nrange_model = "nlso"', "range_model: expected one of"),
        ('[filter]\nheading_mode = "estimated"', "heading_mode: expected one of"),
        ('[filter]\nbias_mode = "Online"', "bias_mode: expected one of"),
        ('[filter]\nspread_rotations = "false"', "spread_rotations: expected true or false"),
        ("[filter]\nparticles = 500.5", "particles: expected an integer"),
        ("[filter]\nparticles = 0", "particles must be >= 1"),
        ("[filter]\nupdate_period = -1.0", "update_period must be > 0"),
        ("[filter]\nlos_sigma = nan", "los_sigma: expected a finite number"),
        ("[filter]\nnlos_fraction = 0.99\ngross_fraction = 0.05", "nlos_fraction + gross_fraction"),
        ("[filter]\ness_threshold = 5.0", "ess_threshold must be in [0, 1]"),
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
        FilterConfig(range_model="nlso")  # type: ignore[arg-type]
    config = TeamConfig.from_dict({"reference": "a", "robots": [{"name": "a"}, {"name": "b"}]})
    with pytest.raises(ConfigError, match="spread_rotations: expected true or false"):
        config.with_filter(spread_rotations="false")
    with pytest.raises(ConfigError, match="heading_mode: expected one of"):
        config.with_modes(heading="magnetometer")
