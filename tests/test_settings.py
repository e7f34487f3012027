"""An episode's settings: one JSON-able value that every command builds the same way."""

from __future__ import annotations

import json

import pytest

from cavenav.cli import FramesMode
from cavenav.episode.settings import _SIZES, FRAME_MODES, SENSOR_FIELDS, EpisodeSettings
from cavenav.errors import ConfigError
from cavenav.sensors.rig import SENSOR_KEYS
from cavenav.world.scenarios import load_scenario

from .conftest import write_room


def test_settings_survive_json_whole() -> None:
    settings = EpisodeSettings(
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
    assert EpisodeSettings.from_dict(json.loads(json.dumps(settings.to_dict()))) == settings
    compressed = EpisodeSettings(exr_compression="zip")
    assert compressed.to_dict()["episode"]["exr_compression"] == "zip"
    assert EpisodeSettings.from_dict(compressed.to_dict()) == compressed
    assert "exr_compression" not in EpisodeSettings().to_dict()["episode"]  # as sweeps wrote it


def test_the_flags_go_over_the_scenario_files_tables(tmp_path) -> None:
    room = write_room(tmp_path)
    room.write_text(room.read_text() + '\n[optics]\nwater = "coastal"\nparticles = 0.5\n')
    cave = load_scenario(str(room))
    settings = EpisodeSettings(
        steps=9, sounder="beam", depth_max_m=8.0, optics={"water": "turbid"}, resolution=(84, 84)
    )
    config = settings.episode_config(cave)
    assert config.max_steps == 9 and config.stuck_after == 50 and not config.shield
    assert config.sensors.sounder == "beam" and config.sensors.depth_max_m == 8.0
    assert config.sensors.optics.water_name == "turbid"  # the flag over the file
    assert config.sensors.optics.particles == 0.5  # the file's, no flag
    assert (config.sensors.camera.width, config.sensors.camera.height) == (84, 84)


def test_bad_settings_are_refused_naming_them() -> None:
    with pytest.raises(ConfigError, match="EXR compression 'lzw'"):
        EpisodeSettings(exr_compression="lzw")
    with pytest.raises(ConfigError, match="width"):
        EpisodeSettings(difficulty={"width": 3.0})
    with pytest.raises(ConfigError, match="sensors: unknown key"):
        EpisodeSettings.from_dict({"episode": {}, "sensors": {"lens": "fisheye"}})


def test_the_names_written_twice_agree_with_where_they_are_declared() -> None:
    # The rig's [sensors] keys, written again in settings so that the command line starts
    # without the kernels; sweep.json's "sensors" are the sensor settings and those sizes.
    assert _SIZES == SENSOR_KEYS
    assert ("sounder", "depth_max_m", "optics", *SENSOR_KEYS) == SENSOR_FIELDS
    assert [mode.value for mode in FramesMode] == list(FRAME_MODES)  # eval --frames
