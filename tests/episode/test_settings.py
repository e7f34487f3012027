"""An episode's configuration: one frozen value that every way of flying builds, with each
default written once."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from cavenav.cli import FramesMode
from cavenav.core.errors import ConfigError
from cavenav.core.types import VehicleBody
from cavenav.episode.on_vehicle import Flight
from cavenav.episode.settings import (
    FRAME_MODES,
    SENSOR_FIELDS,
    EpisodeConfig,
    EpisodeSettings,
    configured,
)
from cavenav.sensors.config import SENSOR_KEYS, SensorConfig
from cavenav.world.current import Current
from cavenav.world.scenarios import load_scenario
from tests.conftest import write_room

SRC = Path(__file__).resolve().parents[2] / "src" / "cavenav"


def test_a_configuration_survives_sweep_json_whole() -> None:
    config = configured(
        steps=40,
        stuck_after=None,
        shield=True,
        save_exr=False,
        sounder="beam",
        depth_max_m=8.0,
        optics={"water": "coastal", "light_power": 5.0},
        resolution=(160, 120),
        sounder_resolution=(16, 12),
        difficulty={"constriction_m": 2.5},
    )
    assert EpisodeConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    compressed = EpisodeConfig(exr_compression="zip")
    assert compressed.to_dict()["episode"]["exr_compression"] == "zip"
    assert EpisodeConfig.from_dict(compressed.to_dict()) == compressed
    assert "exr_compression" not in EpisodeConfig().to_dict()["episode"]  # as sweeps wrote it


def test_what_sweep_json_has_no_place_for_is_refused_rather_than_lost() -> None:
    with pytest.raises(ConfigError, match="a sweep cannot keep body, sensors"):
        EpisodeConfig(body=VehicleBody(length=0.6), sensors=SensorConfig(seed=3)).to_dict()


def test_the_old_names_build_the_same_configuration() -> None:
    new = EpisodeConfig(max_steps=9, seed=4, sensors=SensorConfig(sounder="beam"))
    assert configured(steps=9, noise_seed=4, sounder="beam") == new
    with pytest.warns(DeprecationWarning, match="EpisodeSettings is now EpisodeConfig"):
        assert EpisodeSettings(steps=9, noise_seed=4, sounder="beam") == new
    with pytest.raises(TypeError, match="step"):
        configured(step=9)


def test_the_flags_go_over_the_scenario_files_tables(tmp_path) -> None:
    room = write_room(tmp_path)
    room.write_text(room.read_text() + '\n[optics]\nwater = "coastal"\nparticles = 0.5\n')
    cave = load_scenario(str(room))
    wanted = configured(
        steps=9, sounder="beam", depth_max_m=8.0, optics={"water": "turbid"}, resolution=(84, 84)
    )
    config = wanted.for_episode(cave)
    assert config.max_steps == 9 and config.stuck_after == 50 and not config.shield
    assert config.sensors.sounder == "beam" and config.sensors.depth_max_m == 8.0
    assert config.sensors.optics.water_name == "turbid"  # the flag over the file
    assert config.sensors.optics.particles == 0.5  # the file's, no flag
    assert (config.sensors.camera.width, config.sensors.camera.height) == (84, 84)
    assert config.for_episode(cave) == config  # settling twice changes nothing


def test_a_settled_configuration_has_every_value_an_episode_needs(tmp_path) -> None:
    room = write_room(tmp_path)
    room.write_text(room.read_text() + "\n[water]\ndischarge_m3s = 2.0\n")
    cave = load_scenario(str(room))
    config = EpisodeConfig().for_episode(cave, seed=7)
    assert config.max_steps == 150 and config.seed == 7
    assert config.current == Current(2.0)  # the cave's own flow
    assert EpisodeConfig(seed=3).for_episode(cave, seed=7).seed == 3  # held apart
    assert EpisodeConfig().for_episode(cave).seed == 0  # a scenario file has no seed


def test_bad_settings_are_refused_naming_them() -> None:
    with pytest.raises(ConfigError, match="EXR compression 'lzw'"):
        EpisodeConfig(exr_compression="lzw")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="width"):
        EpisodeConfig(difficulty={"width": 3.0})
    with pytest.raises(ConfigError, match="noise seed must be a whole number"):
        EpisodeConfig(seed=-1)
    with pytest.raises(ConfigError, match="sensors: unknown key"):
        EpisodeConfig.from_dict({"episode": {}, "sensors": {"lens": "fisheye"}})


def test_the_names_sweep_json_keeps_are_the_rigs() -> None:
    assert ("sounder", "depth_max_m", "optics", *SENSOR_KEYS) == SENSOR_FIELDS
    assert [mode.value for mode in FramesMode] == list(FRAME_MODES)  # eval --frames


def test_there_is_one_episode_configuration_type() -> None:
    declared = [
        str(path.relative_to(SRC))
        for path in SRC.rglob("*.py")
        if re.search(r"^class Episode\w*(Config|Settings)\b", path.read_text(), re.M)
    ]
    assert declared == ["episode/settings.py"]
    # a flight on a vehicle's own sensors is a configuration and the vehicle that flies it
    assert [field.name for field in dataclasses.fields(Flight)] == ["config", "vehicle"]
