"""The config tree: defaults run the sim, files override them, mistakes name their key."""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from pathlib import Path

import pytest

from controller.cli.main import main
from controller.config import (
    Config,
    ConfigError,
    LimitsConfig,
    config_from_dict,
    config_to_toml,
    load_config,
)
from drivers.config import FieldError

REPO = Path(__file__).resolve().parents[2]


def test_defaults_are_the_sim_bench() -> None:
    config = load_config(None)
    assert config.robot.arm.type == "sim"
    assert config.gripper.type == "sim" and config.sensor.type == "sim"
    assert config.cameras.rgbd.type == "sim"
    assert config.cameras.rgbd.height_m == pytest.approx(0.4572)
    assert config.cameras.rgbd.tilt_deg == pytest.approx(30.0)


def test_effective_config_round_trips_through_toml() -> None:
    config = Config()
    assert config_from_dict(tomllib.loads(config_to_toml(config))) == config


@pytest.mark.parametrize("name", ["sim.toml", "real_robot.toml", "secured.toml"])
def test_example_configs_load(name: str) -> None:
    config = load_config(REPO / "configs" / name)
    assert isinstance(config, Config)


def test_file_overrides_defaults(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[sim]\nobject = "bowl"\nseed = 7\n[limits]\nmax_force_n = 30\n')
    config = load_config(path)
    assert config.sim.object == "bowl" and config.sim.seed == 7
    assert config.limits.max_force_n == 30.0  # ints are accepted for floats
    assert config.limits.contact_force_n == Config().limits.contact_force_n


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[robot.arm]\nhots = 'x'\n", "unknown key 'robot.arm.hots'"),
        ("[nonsense]\na = 1\n", "unknown key 'nonsense'"),
        ("[limits]\nmax_force_n = 'strong'\n", "'limits.max_force_n' must be a number"),
        ("[sim]\nseed = 1.5\n", "'sim.seed' must be an integer"),
        ("[cameras.rgbd]\ntype = 'webcam'\n", "'cameras.rgbd.type' must be one of"),
        ("[limits]\nworkspace_min_world = [0, 0]\n", "array of 3 values"),
        ("[limits]\ncontact_force_n = 50.0\n", "'limits.contact_force_n' must be below"),
        ("[cameras.rgbd]\ntilt_deg = 95\n", "'cameras.rgbd.tilt_deg' must be in (0, 90)"),
        ("[robot]\nid = 'a/b'\n", "'robot.id' must be a non-empty key-expression chunk"),
        ("[robot]\narm = 3\n", "[robot.arm] must be a table"),
        ("[logging]\nrerun = 'yes'\n", "'logging.rerun' must be true or false"),
        ("this is = = not toml", "not valid TOML"),
    ],
)
def test_bad_config_files_name_the_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        load_config(path)
    assert message in str(error.value)
    assert str(path) in str(error.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        # The probe's failures: each passed validation before.
        ("[limits]\nmax_force_n = nan\n", "'limits.max_force_n' must be a finite number"),
        ("[limits]\nmax_force_n = inf\n", "'limits.max_force_n' must be a finite number"),
        (
            "[limits]\nworkspace_min_world = [nan, -0.4, 0.0]\n",
            "'limits.workspace_min_world' must be a finite number",
        ),
        (
            "[limits]\nmax_tcp_speed_m_s = inf\napproach_speed_m_s = nan\n",
            "must be a finite number",
        ),
        ("[limits]\napproach_speed_m_s = nan\n", "'limits.approach_speed_m_s' must be a finite"),
        ("[limits]\nmax_force_n = -1.0\n", "'limits.max_force_n' must be positive"),
        # Ordered limits, each naming the key that breaks the order.
        ("[limits]\napproach_speed_m_s = 0.3\n", "'limits.approach_speed_m_s' must be at most"),
        (
            "[limits]\napproach_contact_force_n = 6.0\n",
            "'limits.approach_contact_force_n' must be at most contact_force_n",
        ),
        ("[limits]\ncontact_force_n = 40.0\n", "'limits.contact_force_n' must be below"),
        (
            "[limits]\nworkspace_max_world = [0.4, 0.4, -0.1]\n",
            "'limits.workspace_min_world' must be below workspace_max_world",
        ),
        ("[limits]\ntable_clearance_m = 0.0\n", "'limits.table_clearance_m' must be positive"),
        # The device sections (drivers/config.py) too.
        ("[gripper]\nmax_force_n = -5.0\n", "'gripper.max_force_n' must be positive"),
        ("[gripper]\ntcp_port = 70000\n", "'gripper.tcp_port' must be in 1..65535"),
        ("[robot.arm]\nconnect_attempts = 0\n", "'robot.arm.connect_attempts' must be at least"),
        ("[sensor]\nimage_noise_sigma = -1.0\n", "'sensor.image_noise_sigma' must be >= 0"),
        ("[models]\nglobal_patience = -1\n", "'models.global_patience' must be >= 0"),
        ("[models]\ncompute_threads = -2\n", "'models.compute_threads' must be in [0, 256]"),
        ("[sim]\ntable_size_m = [1.2, 0.0]\n", "'sim.table_size_m' must be positive"),
        ("[motion]\nstandoff_m = 0.07\n", "'motion.standoff_m' must be below"),
        ("[models]\nprior = '../../etc/passwd'\n", "'models.prior' must be 1..64 letters"),
        ("[messaging]\nlisten = ['garbage']\n", "'messaging.listen' endpoint 'garbage'"),
        (
            "[messaging]\nconnect = ['tcp/127.0.0.1:99999']\n",
            "'messaging.connect' endpoint 'tcp/127.0.0.1:99999' needs <host>:<port>",
        ),
    ],
)
def test_unsafe_limits_are_refused_naming_the_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "limits.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        load_config(path)
    assert message in str(error.value)
    assert "bad value in" not in str(error.value)  # the key, not only the section


def _float_keys(cls: type, prefix: str = "") -> list[tuple[str, bool]]:
    """Dotted keys of every float and float-vector field of a config section, recursively."""
    keys = []
    for name, hint in typing.get_type_hints(cls).items():
        key = f"{prefix}.{name}" if prefix else name
        args = typing.get_args(hint)
        if dataclasses.is_dataclass(hint):
            keys += _float_keys(hint, key)
        elif hint is float or (args and all(a is float for a in args)):
            keys.append((key, hint is not float))
    return keys


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_every_float_of_every_section_must_be_finite(bad: str) -> None:
    keys = _float_keys(Config)
    assert len(keys) > 60  # the walk finds the tree's floats
    defaults = tomllib.loads(config_to_toml(Config()))
    for key, is_vector in keys:
        *sections, name = key.split(".")
        data: dict = {}
        table = data
        for section in sections:
            table = table.setdefault(section, {})
        value = float(bad)
        if is_vector:
            default = defaults
            for part in key.split("."):
                default = default[part]
            table[name] = [value, *default[1:]]
        else:
            table[name] = value
        with pytest.raises(ConfigError, match=f"'{key}' must be a finite number"):
            config_from_dict(data)


def test_limits_built_in_code_refuse_nan_and_inf() -> None:
    """The checks behind the validator hold for configs built in code (no TOML) too."""
    for field, value in [
        ("max_force_n", math.nan),
        ("contact_force_n", math.nan),
        ("max_tcp_speed_m_s", math.inf),
        ("approach_speed_m_s", math.nan),
        ("workspace_min_world", (math.nan, -0.4, 0.0)),
        ("workspace_max_world", (math.inf, 0.4, 0.6)),
    ]:
        with pytest.raises(FieldError) as error:
            dataclasses.replace(LimitsConfig(), **{field: value})
        assert error.value.field in (field, "workspace_min_world")


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")


def test_cli_config_show(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "show"]) == 0
    shown = tomllib.loads(capsys.readouterr().out)
    assert shown["robot"]["id"] == "sim"
    bad = tmp_path / "bad.toml"
    bad.write_text("[sim]\nobjekt = 'mug'\n")
    assert main(["config", "show", "--config", str(bad)]) == 2
    assert "unknown key 'sim.objekt'" in capsys.readouterr().err


def test_the_global_update_takes_its_settings_from_the_models_section() -> None:
    from types import SimpleNamespace

    from controller.perception.learned import LearnedPerception
    from models.touch.global_fit import GlobalSettings

    config = config_from_dict(
        {
            "models": {
                "global_learning_rate": 0.02,
                "global_iterations": 7,
                "global_patience": 2,
                "global_camera_constraints": False,
            }
        }
    )
    settings = LearnedPerception.global_settings.fget(SimpleNamespace(config=config))
    assert (settings.learning_rate, settings.iterations, settings.patience) == (0.02, 7, 2)
    assert settings.camera_constraints is False
    default = LearnedPerception.global_settings.fget(SimpleNamespace(config=Config()))
    assert default.camera_constraints is True
    assert default.patience is None is GlobalSettings().patience  # the config's default: off
