"""The safety shield judges from what a real vehicle has: depth, sounders, its memory."""

from __future__ import annotations

import numpy as np
import pytest

from cavenav.actions import parse_action
from cavenav.episode.loop import EpisodeConfig, run_episode
from cavenav.pilots.geometric import GeometricPilot
from cavenav.pilots.random_pilot import RandomPilot
from cavenav.shield import DepthMemory, Shield, move_points
from cavenav.types import Action, Observation, Pose
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


def test_the_shield_and_the_geometric_pilot_keep_one_set_of_margins() -> None:
    from cavenav.pilots.geometric import GeometricPilotConfig
    from cavenav.shield import Margins, ShieldConfig

    assert GeometricPilotConfig().margins == ShieldConfig().margins == Margins()
    assert GeometricPilotConfig().corridor_radius(tight=True) == pytest.approx(0.21 + 0.1, 0.01)


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
