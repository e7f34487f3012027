"""The safety shield judges from what a real vehicle has: depth, sounders, its memory."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from cavenav.actions import parse_action
from cavenav.episode.loop import EpisodeConfig, run_episode
from cavenav.errors import ConfigError
from cavenav.pilots.geometric import GeometricPilot
from cavenav.pilots.random_pilot import RandomPilot
from cavenav.sensors.rig import SensorRig
from cavenav.shield import DepthMemory, Margins, Shield, Surroundings, move_hazard, move_points
from cavenav.types import Action, Observation, Pose, VehicleBody
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import ExitPortal, Scenario

from .conftest import box_room
from .conftest import synthetic_observation as seen


def judged(action: str, *observations: Observation):
    shield = Shield()
    for obs in observations:
        shield.observe(obs)
    return shield.judge(parse_action(action))


def test_a_safe_move_in_open_water_passes_untouched() -> None:
    verdict = judged("forward 1 m, turn left 15 deg", seen(np.inf))
    assert not verdict.intervened and verdict.reason == ""


def test_no_forward_motion_toward_an_obstacle_within_1_5_m() -> None:
    verdict = judged("forward 1 m, turn left 5 deg", seen(1.3, d_top=2.5, d_bottom=2.5))
    assert verdict.intervened and verdict.action.forward <= 0
    assert "within 1.5 m" in verdict.reason


def test_inside_the_standoff_forward_is_slow_and_comes_with_a_shift() -> None:
    verdict = judged("forward 1 m", seen(np.inf, d_top=1.2, d_bottom=4.0))  # ceiling near
    assert verdict.action.forward == pytest.approx(0.2)
    assert verdict.action.yaw_deg or verdict.action.right or verdict.action.up
    assert "standoff" in verdict.reason


def test_a_sideways_move_into_space_never_seen_is_refused() -> None:
    verdict = judged("strafe right 1 m", seen(np.inf))  # nothing beside is in view yet
    assert verdict.action == Action()
    assert "never seen free" in verdict.reason and "right" in verdict.reason


def test_space_seen_from_behind_becomes_known_after_moving_into_it() -> None:
    # From 3 m back the camera saw the space beside where the vehicle now is.
    first = seen(np.inf)
    later = seen(np.inf, previous_action=Action(forward=1.0))
    latest = seen(np.inf, previous_action=Action(forward=1.0))
    verdict = judged("strafe right 0.5 m", first, later, latest)
    assert not verdict.intervened, verdict.reason


def test_an_ascent_is_bounded_by_the_upward_sounder() -> None:
    assert not judged("ascend 1 m", seen(np.inf, d_top=3.0)).intervened
    verdict = judged("ascend 2 m", seen(np.inf, d_top=2.0))
    assert verdict.intervened and verdict.action.up < 2.0 - 0.3


def test_the_memory_moves_remembered_surfaces_by_the_executed_action() -> None:
    memory = DepthMemory()
    memory.update(seen(5.0), None)
    before = memory.cloud.copy()
    memory.update(seen(np.inf), Action(forward=1.0, yaw_deg=90.0))
    after = memory.cloud[: len(before)]  # the new frame adds its points behind
    assert np.allclose(after, move_points(before, Action(forward=1.0, yaw_deg=90.0)), atol=1e-5)
    # The wall 5.2 m ahead is, after turning left and moving 1 m, 5.2 m right and 1 m back.
    ahead = np.argmin(np.abs(before[:, 1]) + np.abs(before[:, 2]) - before[:, 0])
    assert np.allclose(before[ahead], (5.2, 0.0, 0.0), atol=0.05)
    assert np.allclose(after[ahead], (-1.0, -5.2, 0.0), atol=0.05)


def test_the_geometric_pilot_remembers_with_the_shields_memory() -> None:
    pilot = GeometricPilot()
    pilot.decide(seen(6.0))
    assert isinstance(pilot.memory, DepthMemory) and len(pilot.memory.frames) == 1


@pytest.mark.slow
def test_the_random_pilot_under_the_shield_does_not_collide(room_scenario: Scenario) -> None:
    config = EpisodeConfig(max_steps=60, save_frames=False, plots=False, shield=True)
    result = run_episode(room_scenario, RandomPilot(seed=3), config)
    assert result.summary["collisions"] == 0 and result.termination != "collision"
    assert result.summary["shield_interventions"] > 0
    shielded = [s for s in result.steps if "shield" in s]
    assert len(shielded) == result.summary["shield_interventions"]
    assert all(s["action"] == s["shield"]["replacement"] for s in shielded)


def test_without_the_shield_the_random_pilot_collides(room_scenario: Scenario) -> None:
    config = EpisodeConfig(max_steps=60, save_frames=False, plots=False)
    result = run_episode(room_scenario, RandomPilot(seed=3), config)
    assert result.termination == "collision" and result.summary["shield"] is False


def test_a_move_that_slants_down_keeps_clear_of_the_floor_the_sounder_reads() -> None:
    # The space behind was seen on the way in; the floor 0.93 m below is taken as level,
    # so backing up while descending 0.64 m would end 0.29 m above it.
    step = Action(forward=1.0)
    way_in = [seen(np.inf, previous_action=step) for _ in range(3)]
    low_floor = seen(np.inf, d_bottom=0.93, previous_action=step)
    verdict = judged("back 1 m, descend 0.64 m", *way_in, low_floor)
    assert verdict.intervened and "floor" in verdict.reason, verdict.reason
    assert verdict.action.up > -0.93 + 0.61


def test_a_pinch_ahead_that_the_body_fits_through_is_no_obstacle() -> None:
    # A wall 1.2 m ahead with a round hole 0.9 m across: the open corridor (the body's
    # section plus 0.3 m) finds it blocked within 1.5 m, the crawlway's (plus 0.1 m, as
    # the geometric pilot flies crawlways) passes. It once read every crawlway's pinch
    # as an obstacle ahead and held the vehicle there.
    rows, cols = np.mgrid[0:480, 0:640]
    hole = np.hypot(rows - 239.5, cols - 319.5) < 0.45 / 1.2 * 640  # focal length 640 px
    verdict = judged("forward 0.2 m, turn left 5 deg", seen(np.where(hole, np.inf, 1.2)))
    assert not verdict.intervened, verdict.reason


@pytest.mark.parametrize("floor_m", [0.55, 0.50])
def test_a_floor_near_below_is_no_crawlway_a_descent_toward_it_is_refused(floor_m: float) -> None:
    # Nearer than the 0.61 m kept in the open, the floor may come at most 5 cm nearer:
    # a surface on one side is no crawlway, where 0.39 m would do.
    verdict = judged("descend 0.1 m", seen(np.inf, d_bottom=floor_m))
    assert verdict.intervened and verdict.action.up >= 0, verdict.reason


def along_a_passage(width_m: float, right_wall_m: float) -> list[Observation]:
    """Two views, 1 m apart, flying along a square passage ``width_m`` across with its
    right wall ``right_wall_m`` away: the memory holds the walls beside the vehicle."""
    rig = SensorRig(RayCaster(box_room(extents=(width_m, 20.0, width_m))))
    x = -width_m / 2 + right_wall_m  # heading -y: the right wall is at -width_m / 2
    first = rig.observe(Pose(x, 1.0, 0.0, 0.0))
    second = replace(rig.observe(Pose(x, 0.0, 0.0, 0.0)), previous_action=Action(forward=1.0))
    return [first, second]


def beside_a_wall(offset_m: float) -> list[Observation]:
    """Along a wall ``offset_m`` to the right, the left wall 1.5 m away, ceiling and floor 1 m."""
    return along_a_passage(2.0, offset_m)


@pytest.mark.parametrize("move", ["strafe right 0.1 m", "forward 0.2 m, strafe right 0.1 m"])
def test_a_move_toward_a_wall_0_5_m_away_is_refused(move: str) -> None:
    # One wall near is no crawlway: 0.4 m would be 10 cm nearer than the 0.5 m it is.
    verdict = judged(move, *beside_a_wall(0.5))
    assert verdict.intervened and verdict.action.right <= 0, verdict.reason
    assert "surface seen" in verdict.reason
    # Away from it, and along it with a turn away, nothing stops the vehicle.
    assert not judged("forward 0.2 m, strafe left 0.1 m", *beside_a_wall(0.5)).intervened
    assert not judged("forward 0.2 m, turn left 5 deg", *beside_a_wall(0.5)).intervened


def test_in_a_passage_pinched_on_both_sides_moves_keep_the_crawlways_margin() -> None:
    # 1.15 m square: every wall 0.575 m away, within the open margin on opposite sides,
    # so no move could keep 0.61 m. Moves keep the 0.39 m reach of the turning body.
    views = along_a_passage(1.15, 0.575)
    for move in ("strafe right 0.1 m", "forward 0.2 m, strafe right 0.1 m", "ascend 0.1 m"):
        assert not judged(move, *views).intervened, move
    assert "surface seen" in judged("strafe right 0.5 m", *views).reason


def test_a_move_hazard_names_the_rule_it_breaks() -> None:
    memory = DepthMemory()
    observation = seen(np.inf, d_top=0.8)
    memory.update(observation, None)
    around = Surroundings.of(observation, memory, VehicleBody(), Margins(), 1.5)

    def kind(move: str) -> str:
        hazard = move_hazard(
            parse_action(move), around, body=VehicleBody(), margins=Margins(), crawlway=False
        )
        return hazard.kind

    assert kind("forward 1 m") == ""
    assert kind("strafe left 0.5 m") == "unseen"
    assert kind("ascend 0.5 m") in {"surface", "sounded"}  # the ceiling 0.8 m above


@pytest.mark.parametrize(
    ("setting", "named"),
    [
        ({"open_m": -0.1}, "open_m = -0.1"),
        ({"crawlway_m": float("nan")}, "crawlway_m = nan"),
        ({"closer_m": -0.05}, "closer_m = -0.05"),
        ({"open_m": 0.2, "crawlway_m": 0.3}, "crawlway_m = 0.3"),
    ],
)
def test_nonsense_margins_are_refused_naming_the_value(setting: dict, named: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(named)):
        Margins(**setting)


@pytest.mark.slow
def test_the_geometric_pilot_crawls_through_under_the_shield_untouched() -> None:
    # 1.15 m square: too narrow for the open margin (0.61 m from every wall), wide enough
    # for the crawlway's. The shield once stopped every step forward there.
    cave = Scenario(
        name="crawlway",
        mesh=box_room(extents=(1.15, 12.0, 1.15)),
        start=Pose(0.0, 5.0, 0.0, 0.0),
        exits=(ExitPortal((0.0, -2.5, 0.0), (0.0, -1.0, 0.0), 3.0),),
    )
    config = EpisodeConfig(max_steps=150, save_frames=False, plots=False, shield=True)
    result = run_episode(cave, GeometricPilot(), config)
    assert result.termination == "exit", result.termination
    assert result.summary["shield_interventions"] == 0


def test_a_climb_slanting_out_of_the_sounders_column_into_space_never_seen_is_refused() -> None:
    # Straight up the upward sounder saw 3 m free; 0.3 m ahead and 0.3 m up lies behind
    # the camera's view and off the sounder's column: nobody saw it.
    verdict = judged("forward 0.2 m, ascend 1 m", seen(np.inf, d_top=3.0))
    assert verdict.intervened and "never seen free" in verdict.reason
    assert not judged("ascend 1 m", seen(np.inf, d_top=3.0)).intervened
