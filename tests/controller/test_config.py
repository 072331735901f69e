"""The config tree: defaults run the sim, files override them, mistakes name their key."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from controller.cli.main import main
from controller.config import (
    Config,
    ConfigError,
    config_from_dict,
    config_to_toml,
    load_config,
)

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
        ("[limits]\ncontact_force_n = 50.0\n", "bad value in [limits]"),
        ("[cameras.rgbd]\ntilt_deg = 95\n", "tilt_deg must be in (0, 90)"),
        ("[robot]\nid = 'a/b'\n", "bad value in [robot]"),
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
