"""The safety shield judges from what a real vehicle has: depth, sounders, its memory."""

from __future__ import annotations

import re
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
import trimesh

from cavenav.core.errors import ConfigError
from cavenav.core.types import Action, Observation, Pose, VehicleBody
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.actions import parse_action
from cavenav.pilots.geometric import GeometricPilot
from cavenav.pilots.random_pilot import RandomPilot
from cavenav.safety.shield import (
    DepthMemory,
    Margins,
    Shield,
    Surroundings,
    move_hazard,
    move_points,
)
from cavenav.sensors.rig import SensorConfig, SensorRig
from cavenav.sim.env import CaveNavEnv
from cavenav.sim.wrappers import SafetyShield, StuckLimit
from cavenav.world.mesh import CaveMesh, make_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import ExitPortal, Scenario
from tests.conftest import box_room
from tests.conftest import synthetic_observation as seen


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
    assert verdict.reason == "the move would end within 0.61 m of the floor (0.93 m away)"
    # 0.32 m down would end 0.61 m above it, a hair short of the 0.612 m kept: 0.1 m.
    assert verdict.action == Action(forward=pytest.approx(-1.0), up=pytest.approx(-0.1))


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
        assert bool(hazard) == bool(hazard.kind)  # the pilot asks "any hazard?" by truth
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


# --------------------------------------------------------------- rules on real geometry
# Each rule judged on what the real sensor rig sees in a small cave built for it, at
# 160x120 (the memory reads every 2nd pixel there). The vehicle ends at the origin heading
# -y, having flown in along -y 1 m a step: its right is -x, its left +x, up +z. Each test
# asserts the exact replacement the shield executes and the reason it records.

Box = tuple[tuple[float, float, float], tuple[float, float, float]]  # (extents, centre)


def cave(passage: Box, *rocks: Box) -> CaveMesh:
    """A closed box ``passage`` with the boxes ``rocks`` standing in it (a pillar, a ledge)."""
    parts = [trimesh.creation.box(extents=e).apply_translation(c) for e, c in (passage, *rocks)]
    joined = trimesh.util.concatenate(parts)
    return make_mesh(joined.vertices, joined.faces, "test-cave")


def flown_in(mesh: CaveMesh, views: int = 3) -> list[Observation]:
    """The last ``views`` observations of a vehicle that flew 1 m a step along -y to the
    origin: the memory holds what the camera saw ahead of it from ``views - 1`` m back."""
    rig = SensorRig(RayCaster(mesh), SensorConfig().with_resolution(160, 120))
    seen_on_the_way = [rig.observe(Pose(0.0, float(back), 0.0, 0.0)) for back in range(views)]
    first, *later = reversed(seen_on_the_way)
    return [first, *(replace(obs, previous_action=Action(forward=1.0)) for obs in later)]


WIDE = ((6.0, 20.0, 6.0), (0.0, 0.0, 0.0))  # walls, ceiling and floor 3 m away


def beside(right_wall_m: float) -> Box:
    """A passage 6 m high with its right wall ``right_wall_m`` from the centre, the left 3 m."""
    width = right_wall_m + 3.0
    return ((width, 20.0, 6.0), (3.0 - width / 2, 0.0, 0.0))


@pytest.fixture(scope="module")
def pillar_ahead() -> list[Observation]:
    """A pillar 0.4 m square whose face is 1 m ahead of the centre (0.8 m from the camera),
    a little right of the axis, in a wide passage."""
    return flown_in(cave(WIDE, ((0.4, 0.4, 6.0), (-0.1, -1.2, 0.0))))


def test_rule_1_a_pillar_0_8_m_ahead_stops_forward_motion(pillar_ahead) -> None:
    verdict = judged("forward 1 m", *pillar_ahead)
    # What is left is the standoff's shift away from it (it is right of the axis): left.
    assert verdict.action == Action(right=pytest.approx(-0.1))
    assert verdict.reason == "obstacle 0.8 m ahead, within 1.5 m: no forward motion"
    # A turn keeps its turn and loses its forward motion: the pillar is still ahead.
    verdict = judged("forward 1 m, turn left 15 deg", *pillar_ahead)
    assert verdict.action == Action(yaw_deg=15.0)
    assert verdict.reason.endswith("m ahead, within 1.5 m: no forward motion")
    # Rule 1 looks along the new heading: turned 45 degrees left the pillar is off it.
    assert not judged("forward 0.2 m, turn left 45 deg", *pillar_ahead).intervened


def test_rule_2_inside_the_standoff_forward_is_0_2_m_with_a_shift_away() -> None:
    views = flown_in(cave(beside(1.2)))  # a wall 1.2 m to the right, within the 2 m standoff
    verdict = judged("forward 1 m", *views)
    assert verdict.action == Action(forward=pytest.approx(0.2), right=pytest.approx(-0.1))
    assert verdict.reason.endswith("inside the 2 m standoff: forward at most 0.2 m")
    verdict = judged("forward 0.2 m", *views)
    assert verdict.action == Action(forward=pytest.approx(0.2), right=pytest.approx(-0.1))
    assert verdict.reason == "inside the standoff, forward motion must come with a turn or a shift"


def test_rule_3_in_the_open_a_move_keeps_0_61_m_from_every_surface_seen() -> None:
    # A wall 0.75 m to the right: 0.5 m toward it would end 0.25 m away, 0.2 m 0.55 m away,
    # both nearer than the body's half-diagonal (0.31 m) plus the open margin (0.3 m).
    verdict = judged("strafe right 0.5 m", *flown_in(cave(beside(0.75))))
    assert verdict.action == Action(right=pytest.approx(0.1))
    assert verdict.reason == "the move would pass within 0.61 m of a surface seen"


def test_rule_3_a_wall_passing_at_0_5_m_lets_a_move_come_5_cm_nearer_not_10() -> None:
    views = flown_in(cave(beside(0.5)))
    verdict = judged("strafe right 0.1 m", *views)
    assert verdict.action == Action(right=pytest.approx(-0.1))  # the standoff's shift away
    assert verdict.reason == "the move would pass within 0.45 m of a surface seen"
    # Turning 5 degrees toward it while going 0.2 m comes 2 cm nearer: allowed.
    assert not judged("forward 0.2 m, turn right 5 deg", *views).intervened


def test_rule_3_in_a_crawlway_a_move_keeps_the_turning_bodys_reach_plus_0_1_m() -> None:
    # 1.15 m square: walls 0.575 m away on every side, a crawlway. 0.2 m right would end
    # 0.375 m from the wall, within the corners' reach (0.29 m) plus 0.1 m; 0.1 m is fine.
    views = flown_in(cave(((1.15, 20.0, 1.15), (0.0, 0.0, 0.0))))
    verdict = judged("strafe right 0.5 m", *views)
    assert verdict.action == Action(right=pytest.approx(0.1))
    assert verdict.reason == "the move would pass within 0.39 m of a surface seen"


def test_rule_3_a_floor_at_the_sounders_edge_counts_as_level_under_the_whole_move() -> None:
    # A ledge 0.93 m below whose edge lies 0.1 m behind the centre, inside the downward
    # sounder's cone; behind it the floor drops to 3 m, but the shield knows the floor only
    # from the sounder and takes it as level. Backing up 1 m while descending 0.64 m
    # passes far from every point seen, yet would end 0.29 m above that plane; the
    # descent it keeps must leave the body's half-diagonal (0.31 m) plus 0.3 m.
    ledge = ((6.0, 9.0, 2.07), (0.0, 0.1 - 4.5, -3.0 + 2.07 / 2))
    views = flown_in(cave(WIDE, ledge), views=5)  # the camera 3.8 m back saw the space behind
    assert views[-1].d_bottom == pytest.approx(0.93, abs=0.01)
    verdict = judged("back 1 m, descend 0.64 m", *views)
    assert verdict.action == Action(forward=pytest.approx(-1.0), up=pytest.approx(-0.1))
    assert verdict.reason == "the move would end within 0.61 m of the floor (0.93 m away)"


def test_rule_3_under_a_low_ceiling_a_climb_is_refused_and_the_shift_is_down() -> None:
    views = flown_in(cave(((6.0, 20.0, 3.7), (0.0, 0.0, -1.15))))  # the ceiling 0.7 m above
    assert views[-1].d_top == pytest.approx(0.7, abs=0.01)
    verdict = judged("ascend 0.2 m", *views)
    assert verdict.action == Action(up=pytest.approx(-0.1))
    assert verdict.reason == "the move would pass within 0.61 m of a surface seen"


def test_rule_4_a_side_never_seen_is_refused_however_far_its_walls() -> None:
    # One view: the space beside the vehicle has not been in the camera's view.
    verdict = judged("forward 0.5 m, strafe right 0.5 m", *flown_in(cave(WIDE), views=1))
    # It keeps what the camera's view takes in beside it, 0.2 m, and the forward move.
    assert verdict.action == Action(forward=pytest.approx(0.5), right=pytest.approx(0.2))
    assert "the move would enter space never seen free" in verdict.reason
    assert "right of the vehicle" in verdict.reason


def test_no_room_to_turn_a_wall_0_25_m_beside_refuses_a_turn() -> None:
    # The corners reach 0.29 m from the centre when the body turns in place: with 5 cm to
    # spare, a wall nearer than 0.34 m at the body's height leaves no room to turn.
    verdict = judged("turn left 15 deg", *flown_in(cave(beside(0.25))))
    assert verdict.action == Action(right=pytest.approx(-0.1))  # away from the wall, unturned
    assert verdict.reason == "a surface 0.25 m beside the centre leaves no room to turn"


@pytest.mark.parametrize(("wall_m", "turns"), [(0.32, False), (0.4, True)])
def test_no_room_to_turn_keeps_5_cm_beyond_the_corners_reach(wall_m: float, turns: bool) -> None:
    verdict = judged("turn left 15 deg", *flown_in(cave(beside(wall_m))))
    assert verdict.intervened is not turns, verdict.reason
    assert turns or verdict.reason.endswith("m beside the centre leaves no room to turn")


def test_the_shield_wrapper_stops_a_vehicle_driven_at_a_pillar_and_steps_it_aside() -> None:
    # End to end: the environment renders, the wrapper judges, the vehicle executes the
    # replacement. Driven straight at a pillar whose face is 3 m ahead, it flies 2 m, then
    # with the face 1 m ahead (0.8 m from the camera) sidesteps away from it instead.
    scenario = Scenario(
        name="pillar",
        mesh=cave(WIDE, ((0.4, 0.4, 6.0), (-0.1, -1.2, 0.0))),
        start=Pose(0.0, 2.0, 0.0, 0.0),
        exits=(ExitPortal((0.0, -8.0, 0.0), (0.0, -1.0, 0.0), 3.0),),
    )
    env = SafetyShield(CaveNavEnv(scenario, resolution=(160, 120)))
    env.reset(seed=0)
    flown = [env.step("forward 1 m")[4] for _ in range(4)]
    assert [step["shield"] for step in flown[:2]] == [None, None]
    for step in flown[2:]:
        assert step["shield"] == {
            "proposed": "forward 1 m",
            "replacement": "strafe left 0.1 m",
            "reason": "obstacle 0.8 m ahead, within 1.5 m: no forward motion",
        }
    assert [(step["pose"]["x"], step["pose"]["y"]) for step in flown] == [
        pytest.approx(xy, abs=1e-6) for xy in [(0.0, 1.0), (0.0, 0.0), (0.1, 0.0), (0.2, 0.0)]
    ]  # left is +x heading -y
    assert not any(step["collision"] for step in flown) and env.interventions == 2


def test_the_shield_wrapper_refuses_an_environment_that_is_not_a_cave_in_one_line() -> None:
    with pytest.raises(TypeError, match="^SafetyShield wraps a CaveNavEnv, not CartPoleEnv$"):
        SafetyShield(gym.make("CartPole-v1"))
    stacked = SafetyShield(StuckLimit(CaveNavEnv("S1", resolution=(64, 48)), steps=5))
    assert stacked.reset(seed=0)[1]["shield"] is None  # a wrapped cave is a cave


def test_stuck_limits_measures_of_headway_still_import_from_the_wrappers() -> None:
    from cavenav.safety import headway
    from cavenav.sim import wrappers

    assert (wrappers.STUCK_PROGRESS_M, wrappers.GROUND_CELL_M) == (0.5, 2.0)
    assert wrappers.STUCK_PROGRESS_M is headway.STUCK_PROGRESS_M
    assert wrappers.GROUND_CELL_M is headway.GROUND_CELL_M
