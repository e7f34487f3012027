"""The cave line as an episode flies it: off by default, a setting, recorded, and no help
to the geometric pilot, which never looks at it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import ConfigError
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.kinematics import apply
from cavenav.pilots.geometric import GeometricPilot
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import load_scenario, procedural_scenario
from tests.world.test_guideline import write_guided_room

QUIET = EpisodeConfig(save_frames=False, plots=False)


def test_no_cave_has_a_line_unless_asked() -> None:
    assert EpisodeConfig().guideline is None
    assert EpisodeConfig().load("S1", 0).guideline is None  # as in the paper


def test_the_setting_lays_the_line_takes_it_away_or_keeps_the_caves_own(tmp_path: Path) -> None:
    plain = load_scenario(str(write_guided_room(tmp_path)))
    laid = EpisodeConfig(guideline=True).cave(plain)
    assert laid.guideline is not None and laid.guideline.colour == "white"
    assert laid.mesh is plain.mesh and laid.start == plain.start
    assert EpisodeConfig(guideline=True).cave(laid) is laid  # laid once
    assert EpisodeConfig(guideline=False).cave(laid).guideline is None
    assert EpisodeConfig().cave(laid) is laid and EpisodeConfig().cave(plain) is plain
    yellow = EpisodeConfig(guideline_colour="yellow")
    assert yellow.cave(plain).guideline is None  # a colour alone lays no line
    assert yellow.cave(laid).guideline.colour == "yellow"  # type: ignore[union-attr]
    own = tmp_path / "own"
    own.mkdir()
    files = load_scenario(str(write_guided_room(own, 'guideline = "yellow"\n')))
    assert EpisodeConfig().load(str(own / "room.toml"), 0).guideline.colour == "yellow"  # type: ignore[union-attr]
    assert EpisodeConfig(guideline=False).cave(files).guideline is None


def test_a_sweep_keeps_the_line_in_sweep_json() -> None:
    config = EpisodeConfig(guideline=True, guideline_colour="yellow")
    kept = json.loads(json.dumps(config.to_dict()))
    assert kept["episode"]["guideline"] is True and kept["episode"]["guideline_colour"] == "yellow"
    assert EpisodeConfig.from_dict(kept) == config
    plain = EpisodeConfig().to_dict()["episode"]
    assert "guideline" not in plain and "guideline_colour" not in plain  # as sweeps wrote it


@pytest.mark.parametrize(
    ("settings", "message"),
    [({"guideline_colour": "red"}, "choose one of white, yellow"),
     ({"guideline": 1}, "guideline must be true, false or unset")],
)  # fmt: skip
def test_a_bad_line_setting_is_refused(settings: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        EpisodeConfig(**settings)


def test_the_run_folder_records_the_line_flown(tmp_path: Path) -> None:
    cave = load_scenario(str(write_guided_room(tmp_path)))
    config = replace(QUIET, max_steps=2, guideline=True, guideline_colour="yellow")
    run_episode(cave, GeometricPilot(), config, tmp_path / "run")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["guideline"]["colour"] == "yellow" and summary["guideline"]["ties"] >= 3
    assert summary["config"]["guideline"] is True
    plain = run_episode(cave, GeometricPilot(), replace(QUIET, max_steps=1))
    assert plain.summary["guideline"] is None


def test_the_top_down_plot_draws_the_line_in_its_colour(tmp_path: Path) -> None:
    cave = load_scenario(str(write_guided_room(tmp_path)))
    config = replace(QUIET, max_steps=2, plots=True, guideline=True, guideline_colour="yellow")
    run_episode(cave, GeometricPilot(), config, tmp_path / "lined")
    run_episode(cave, GeometricPilot(), replace(config, guideline=False), tmp_path / "plain")

    def goldenrod_pixels(run: str) -> int:
        image = np.asarray(Image.open(tmp_path / run / "topdown.png").convert("RGB"), int)
        return int((np.abs(image - (218, 165, 32)).max(axis=2) <= 12).sum())

    assert goldenrod_pixels("lined") > 50
    assert goldenrod_pixels("plain") == 0


def test_the_geometric_pilot_takes_no_notice_of_the_line_in_colour() -> None:
    """It decides from depth and the sounders alone: the line's pixels in the colour image
    and the prompt's flag change nothing."""
    cave = procedural_scenario("S1", 0)
    laid = cave.with_guideline()
    caster = RayCaster(cave.mesh)
    on, off = SensorRig(caster, SensorConfig(), laid.guideline), SensorRig(caster)
    plain, shown = GeometricPilot(), GeometricPilot()
    pose, seen = cave.start, 0
    for step in range(25):
        line, bare = on.observe(pose, step), off.observe(pose, step)
        seen += int((line.rgb != bare.rgb).any())
        decision = plain.decide(bare)
        assert shown.decide(replace(bare, rgb=line.rgb, guideline="white")) == decision
        pose = apply(pose, decision.action)
    assert seen > 10  # the line was in view


@pytest.mark.slow
def test_the_geometric_pilot_flies_s1_the_same_with_and_without_the_line() -> None:
    cave = load_scenario("S1", 0)
    flights = [run_episode(cave, GeometricPilot(), replace(QUIET, guideline=g)) for g in (False, True)]  # fmt: skip  # noqa: E501
    assert flights[1].summary["guideline"] is not None
    actions = [[step["action"] for step in flight.steps] for flight in flights]
    assert actions[0] == actions[1] and flights[0].termination == flights[1].termination == "exit"
