"""Team configs: a typo or an impossible value is a clear :class:`ConfigError`, never a silent
default or a crash later in the filter."""

from __future__ import annotations

import importlib
import re
from dataclasses import fields
from pathlib import Path

import pytest

from relloc.config import (
    AssociationConfig,
    ConfigError,
    FilterConfig,
    LikelihoodConfig,
    TeamConfig,
    UwbConfig,
)
from relloc.config.moved import MOVED, moved_message

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
        (
            '[filter.likelihood]\nrange_model = "nlso"',
            "filter.likelihood.range_model: expected one of",
        ),
        ('[filter.self_calibration]\nheading_mode = "estimated"', "heading_mode: expected one of"),
        ('[filter.self_calibration]\nbias_mode = "Online"', "bias_mode: expected one of"),
        (
            '[[robots]]\nname = "c"\nodom_zero_stamps = "false"',
            "odom_zero_stamps: expected true or false",
        ),
        ("[filter]\nparticles = 500.5", "particles: expected an integer"),
        ("[filter]\nparticles = 0", "particles must be >= 1"),
        ("[filter]\ninit_window = -1.0", "init_window must be >= 0"),
        ("[uwb]\nlos_sigma = nan", "los_sigma: expected a finite number"),
        ("[uwb]\nsigma = 0.0", "uwb.sigma must be > 0"),
        (
            "[filter.resampling]\nrotation_kernel = 5.0",
            "filter.resampling.rotation_kernel must be in [0, 1]",
        ),
        ("[association]\nsigma_det = -0.1", "association.sigma_det must be > 0"),
        ("[filter.likelihood]\nparticles = 10", "filter.likelihood: unknown key"),
        ("[filter]\nlikelihood = 3", "filter.likelihood must be a table"),
        ("[uwb.pairs.n_1-n_2]\nbias = 0.3\nscale = 0.0", "range scale must be > 0"),
        ('[uwb.pairs.n_1-n_2]\nbias = 0.3\nsigma = "x"', "sigma: expected a finite number"),
        ("area = [-inf, inf, -1.0, 1.0]", "area must be"),
        ("[uwb]\ndefault_bias = inf", "default_bias: expected a finite number"),
        ("uwb = 3", "malformed config"),
        ('[[robots]]\nname = "c"\nodom_mode = "wheels"', "odom_mode: expected one of"),
        ("dimension = 4", "dimension must be 2 or 3"),
        ("dimension = 2.5", "dimension: expected an integer"),
    ],
)
def test_bad_values_are_config_errors(tmp_path: Path, extra: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("+", r"\+")):
        _load(tmp_path, extra)


def test_a_flying_team_says_so_and_a_ground_team_writes_no_dimension(tmp_path: Path) -> None:
    flying = _load(tmp_path, "dimension = 3")
    assert flying.dimension == 3
    assert TeamConfig.from_dict(flying.to_dict()).dimension == 3
    ground = _load(tmp_path, "")
    assert ground.dimension == 2 and "dimension" not in ground.to_dict()


def test_a_folder_is_not_a_config(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        TeamConfig.load(tmp_path)


def test_configs_made_in_code_are_checked_too() -> None:
    """A config made in code (``FilterConfig(...)``, ``with_filter``, ``with_modes``) goes
    through the same checks as one read from a file."""
    with pytest.raises(ConfigError, match="range_model: expected one of"):
        LikelihoodConfig(range_model="nlso")  # type: ignore[arg-type]
    config = TeamConfig.from_dict({"reference": "a", "robots": [{"name": "a"}, {"name": "b"}]})
    with pytest.raises(ConfigError, match="odom_zero_stamps: expected true or false"):
        config.with_robot("a", odom_zero_stamps="false")
    with pytest.raises(ConfigError, match="heading_mode: expected one of"):
        config.with_modes(heading="magnetometer")


@pytest.mark.parametrize(
    ("key", "section"),
    [
        ('range_model = "nlos"', "likelihood"),
        ("unseen_speed = 0.1", "odometry"),
        ("rotation_kernel = 0.1", "resampling"),
        ('heading_mode = "estimate"', "self_calibration"),
        ("selfcal_particles = 10", "self_calibration"),
        ("min_particles = 10", "adaptive"),
    ],
)
def test_an_old_flat_filter_key_names_its_new_place(tmp_path: Path, key: str, section: str) -> None:
    name = key.split(" ")[0]
    with pytest.raises(
        ConfigError, match=rf"filter\.{name} has moved to the \[filter\.{section}\] table"
    ):
        _load(tmp_path, f"[filter]\n{key}")


def test_the_filter_sections_round_trip_and_take_changes_by_name(tmp_path: Path) -> None:
    config = _load(
        tmp_path,
        '[filter]\nparticles = 700\n[filter.likelihood]\nrange_model = "symmetric"\n'
        '[filter.self_calibration]\nbias_mode = "online"\n[uwb]\nlos_sigma = 0.12\n'
        "[association]\nd_th = 0.2",
    )
    fc = config.filter
    assert (fc.particles, fc.likelihood.range_model, fc.self_calibration.bias_mode) == (
        700,
        "symmetric",
        "online",
    )
    assert (config.uwb.los_sigma, config.association.d_th) == (0.12, 0.2)
    assert TeamConfig.from_dict(config.to_dict()) == config
    assert "[filter.likelihood]" in config.to_toml() and "[association]" in config.to_toml()
    changed = config.with_filter(particles=5, selfcal_particles=7, min_particles=300)
    assert (changed.filter.particles, changed.filter.self_calibration.selfcal_particles) == (5, 7)
    assert (
        changed.filter.adaptive.min_particles == 300 and changed.filter.likelihood == fc.likelihood
    )
    assert FilterConfig.choices("heading_mode") == ("compass", "estimate")
    with pytest.raises(TypeError, match="no field 'particle'"):
        config.with_filter(particle=5)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            "[filter.likelihood]\nsigma_uwb = 0.2",
            "[filter.likelihood] sigma_uwb moved to [uwb] sigma",
        ),
        (
            "[filter.likelihood]\nlos_sigma = 0.2",
            "[filter.likelihood] los_sigma moved to [uwb] los_sigma",
        ),
        ("[filter]\nsigma_uwb = 0.2", "[filter.likelihood] sigma_uwb moved to [uwb] sigma"),
        (
            "[filter.adaptive]\nkld_bin = 0.3",
            "[filter.adaptive] kld_bin is no longer a setting: it is the constant relloc.filter.adaptive.KLD_BIN (0.2 m)",
        ),
        (
            "[filter]\nupdate_period = 0.2",
            "[filter] update_period is no longer a setting: it is the constant "
            "relloc.localizers.grid.UPDATE_PERIOD (0.1 s)",
        ),
        ("[filter.odometry]\nprocess_noise = 0.01", "relloc.filter.motion.PROCESS_NOISE"),
        (
            "[filter.adaptive]\nmc_tolerance_ordered = 0.012",
            "the ordered resampling it switched on was removed",
        ),
        (
            "[filter.association]\nd_th = 0.2",
            "[filter.association] d_th moved to [association] d_th",
        ),
        ("[filter.association]\ndet_gate_sigmas = 3.0", "relloc.stages.association.GATE_SIGMAS"),
        (
            "[association]\ndet_gate_sigmas = 3.0",
            "[filter.association] det_gate_sigmas is no longer a setting: it is the constant relloc.stages.association.GATE_SIGMAS",
        ),
    ],
)
def test_an_old_key_is_an_error_that_names_the_change(
    tmp_path: Path, extra: str, message: str
) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        _load(tmp_path, extra)


def test_an_old_name_in_code_names_the_change_too() -> None:
    config = TeamConfig.from_dict({"reference": "a", "robots": [{"name": "a"}, {"name": "b"}]})
    with pytest.raises(
        ConfigError, match=re.escape("[filter.likelihood] sigma_uwb moved to [uwb] sigma")
    ):
        config.with_filter(sigma_uwb=0.2)
    with pytest.raises(ConfigError, match=re.escape("relloc.filter.base.ESS_THRESHOLD (0.5)")):
        config.filter.with_changes(ess_threshold=0.4)


@pytest.mark.parametrize("key", sorted(MOVED))
def test_every_old_key_is_gone_and_what_it_names_exists(key: str) -> None:
    """An old key is in no section any more; the constant its message names exists with the
    value the message gives (the old default), and a moved key exists at its new place."""
    assert FilterConfig.section_of(key) is None
    message = moved_message(key)
    assert message is not None
    constant = re.search(r"the constant ([\w.]+) \(([-\d.]+)", message)
    if constant is not None:
        path, value = constant.groups()
        module, _, name = path.rpartition(".")
        owner: object
        try:
            owner = importlib.import_module(module)
        except ModuleNotFoundError:  # a dataclass field's default: module.Class.field
            module, _, cls = module.rpartition(".")
            owner = getattr(importlib.import_module(module), cls)
        assert getattr(owner, name) == pytest.approx(float(value))
    moved = re.search(r"moved to \[(\w+)\] (\w+)", message)
    if moved is not None:
        table, name = moved.groups()
        assert name in {
            f.name for f in fields({"uwb": UwbConfig, "association": AssociationConfig}[table])
        }
    assert constant or moved or "no longer a setting" in message


def test_at_most_thirty_filter_tunables() -> None:
    top = [f.name for f in fields(FilterConfig) if f.name not in FilterConfig.sections()]
    tunables = top + [f.name for cls in FilterConfig.sections().values() for f in fields(cls)]
    assert len(tunables) == 24 <= 30
    assert "kind" in top
