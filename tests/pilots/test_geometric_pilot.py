"""The geometric baseline follows the prompt's strategy from what a VLM would see."""

from __future__ import annotations

import inspect
import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from cavenav.core.types import Action, Observation, Pose, VehicleBody
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion import kinematics
from cavenav.motion.actions import DEFAULT_SPACE, format_action, parse_action
from cavenav.pilots.base import Pilot
from cavenav.pilots.geometric import GeometricPilot, GeometricPilotConfig, _ViewOpening
from cavenav.safety.cave_map import Opening
from cavenav.safety.shield import Hazard, Shield, Surroundings, crawlway_move, move_hazard
from cavenav.sensors.depth import normalise_depth
from cavenav.sensors.rig import SensorRig
from cavenav.world.collision import swept_collision
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import ExitPortal, Scenario
from tests.conftest import box_room
from tests.conftest import synthetic_observation as synthetic


def observe(room_extents, pose: Pose) -> Observation:
    return SensorRig(RayCaster(box_room(extents=room_extents))).observe(pose)


def test_it_is_a_pilot_that_sees_only_observations() -> None:
    pilot = GeometricPilot()
    assert isinstance(pilot, Pilot)
    assert list(inspect.signature(pilot.decide).parameters) == ["observation"]


def test_open_water_ahead_means_full_speed() -> None:
    decision = GeometricPilot().decide(synthetic(np.inf))
    assert decision.action.forward == 1.0
    assert decision.action.yaw_deg == 0.0


@pytest.mark.filterwarnings("error")  # no mean of an empty slice either
@pytest.mark.parametrize(("width", "height"), [(8192, 10), (10, 8192), (1, 1)])
def test_any_image_a_camera_may_give_is_read_even_a_wide_flat_one(width: int, height: int) -> None:
    depth = np.full((height, width), np.inf, np.float32)
    wide = replace(synthetic(np.inf), depth_m=depth, depth_png=normalise_depth(depth),
                   rgb=np.zeros((height, width, 3), np.uint8))  # fmt: skip
    assert GeometricPilot().decide(wide).action.forward == 1.0


def test_answers_in_the_vlm_form() -> None:
    decision = GeometricPilot().decide(observe((8, 40, 8), Pose(0, 15, 0, 0)))
    assert parse_action(decision.action_text) == decision.action
    assert DEFAULT_SPACE.is_valid(decision.action)
    for part in ("Situation:", "Constraints:", "Choice:"):
        assert part in decision.justification


def test_no_forward_motion_within_1_5_m_of_an_obstacle_ahead() -> None:
    decision = GeometricPilot().decide(synthetic(1.2))
    assert decision.action.forward == 0.0
    assert abs(decision.action.yaw_deg) >= 45  # manoeuvre toward a clearer side
    assert "1.5 m" in decision.justification


def test_below_the_standoff_forward_is_slow_and_combined_with_another_motion() -> None:
    # A corridor 3 m wide: the walls are 1.5 m away, inside the 2.0 m standoff.
    decision = GeometricPilot().decide(observe((3, 40, 6), Pose(0, 15, 0, 0)))
    action = decision.action
    assert 0 < action.forward <= 0.2
    assert action.yaw_deg or action.right or action.up


def test_re_centres_between_ceiling_and_floor() -> None:
    decision = GeometricPilot().decide(synthetic(np.inf, d_top=4.0, d_bottom=2.0))
    assert decision.action.up == pytest.approx(1.0)


def test_turns_toward_the_open_side() -> None:
    # Heading 30 degrees to the right of a long corridor's axis: the passage opens left.
    decision = GeometricPilot().decide(observe((6, 60, 6), Pose(0, 20, 0, np.radians(-30))))
    assert decision.action.yaw_deg > 0


def test_boxed_in_it_searches_one_way_round_never_back_and_forth() -> None:
    # The loop it once fell into: at 180 degrees the search flipped, the next step flipped
    # it back, and it alternated left and right on one spot for hundreds of steps.
    pilot = GeometricPilot()
    turns = [pilot.decide(synthetic(1.0)).action.yaw_deg for _ in range(10)]
    assert all(turn == turns[0] for turn in turns) and turns[0] != 0
    assert abs(sum(turns)) >= 360


def test_turning_back_and_forth_on_one_spot_becomes_a_one_way_search(monkeypatch) -> None:
    # Hemmed in so that only its turns are carried out, it would turn toward the way on,
    # overshoot and turn back for ever; six such turns in place start the search instead.
    def turns_only(self, action: Action, around) -> tuple[Action, str]:
        return Action(yaw_deg=action.yaw_deg), "hemmed in: turning only"

    monkeypatch.setattr(GeometricPilot, "_keep_clear", turns_only)
    pilot, heading, turns = GeometricPilot(), 0.0, []
    for _ in range(16):
        view = observe((4, 14, 4), Pose(0, 0, 0, math.radians(heading)))  # a wall 7 m ahead
        yaw = pilot.decide(view).action.yaw_deg
        heading += yaw
        turns.append(yaw)
    assert any(turns[i : i + 4] == [turns[i]] * 4 and abs(turns[i]) == 45 for i in range(10))


def corridor(extents: tuple[float, float, float], start_y: float, exit_y: float) -> Scenario:
    """A closed box along y; the exit plane at ``exit_y``, facing out toward its end."""
    outward = 1.0 if exit_y > start_y else -1.0
    return Scenario(
        name="corridor",
        mesh=box_room(extents=extents),
        start=Pose(0.0, start_y, 0.0, 0.0),  # heading -y
        exits=(ExitPortal((0.0, exit_y, 0.0), (0.0, outward, 0.0), 3.0),),
    )


def test_a_dead_end_is_searched_then_backed_out_of() -> None:
    # Facing a passage that ends blind 20 m ahead; the exit is behind the start.
    cave = corridor((6.0, 40.0, 5.0), start_y=0.0, exit_y=17.0)
    result = run_episode(cave, GeometricPilot(), EpisodeConfig(max_steps=150, plots=False))
    assert result.termination == "exit"
    ys = [pose.y for pose in result.poses]
    assert min(ys) < -14.0  # it went to look
    backing = [s["justification"] for s in result.steps if "dead end" in s["justification"]]
    assert backing, "it never said it was backing out of a dead end"


def test_a_passage_just_wider_than_the_body_is_traversed() -> None:
    # 0.9 m square: 0.28 m to spare either side of the 0.34 m wide body, 0.33 m above and
    # below it. The full corridor margin reads it as blocked; the crawlway margin fits.
    cave = corridor((0.9, 16.0, 0.9), start_y=7.0, exit_y=-5.0)
    result = run_episode(cave, GeometricPilot(), EpisodeConfig(max_steps=120, plots=False))
    assert result.termination == "exit", result.summary["termination"]
    assert result.summary["collisions"] == 0
    assert "crawlway" in result.steps[0]["justification"]


def test_a_passage_narrower_than_the_full_margin_is_flown_without_stopping() -> None:
    # 1.15 m square: wide enough that the full corridor reads open ahead, too narrow for
    # the full 0.6 m keep-clear margin from every wall. It once turned 5 degrees left and
    # right on the spot until the episode ended.
    cave = corridor((1.15, 24.0, 1.15), start_y=11.0, exit_y=-9.0)
    result = run_episode(cave, GeometricPilot(), EpisodeConfig(max_steps=150, plots=False))
    assert result.termination == "exit", result.summary["termination"]
    assert result.summary["collisions"] == 0


@pytest.mark.parametrize("setting", [{"stride": 0}, {"stride": -5}, {"columns": 0}])
def test_a_sampling_stride_below_one_is_refused_where_it_is_set(setting: dict) -> None:
    from cavenav.core.errors import ConfigError
    from cavenav.safety.shield import DepthMemory

    with pytest.raises(ConfigError, match="stride"):
        GeometricPilotConfig(**setting)
    with pytest.raises(ConfigError, match="stride"):
        DepthMemory(**setting)


def hall_with_a_rock_beside(rock_x: float) -> RayCaster:
    """An 8 m wide hall along y, and a rock 0.6 m thick, 1.6 m long, standing at ``rock_x``."""
    hall = trimesh.creation.box(extents=(8.0, 40.0, 6.0))
    rock = trimesh.creation.box(extents=(0.6, 1.6, 2.0))
    rock.apply_translation((rock_x, 0.0, 0.0))
    both = trimesh.util.concatenate([hall, rock])
    return RayCaster(make_mesh(both.vertices, both.faces, "hall-with-rock"))


def test_a_rock_beside_it_out_of_view_is_never_strafed_into() -> None:
    # The collision of the issue: the right wall 1.9 m away, inside the standoff; the left
    # wall 6 m away, too far ahead to count; a rock 0.6 m to the left, beside the body and
    # out of the 53-degree view. It once chose "forward 0.2 m, strafe left 0.5 m" ("away
    # from the nearer wall") into the rock. Now it looks before it strafes.
    caster = hall_with_a_rock_beside(rock_x=-1.2)
    rig, pilot, pose = SensorRig(caster), GeometricPilot(), Pose(-2.1, 0.0, 0.0, 0.0)
    actions = []
    for _ in range(6):
        action = pilot.decide(rig.observe(pose)).action
        end = kinematics.apply(pose, action)
        assert not swept_collision(caster, VehicleBody(), pose, end), format_action(action)
        actions.append(action)
        pose = end
    # It turns to look at the left side it meant to move to, and having seen the rock
    # there, never moves toward it.
    assert any(a.yaw_deg > 0 for a in actions), [format_action(a) for a in actions]
    assert all(a.right >= 0 for a in actions)


def test_every_move_it_makes_enters_only_space_it_has_seen_free() -> None:
    # The shield's own judgement of a move (rules 3 and 4, cavenav.safety.shield.move_hazard),
    # from the shield's memory moved by what was executed: flown past the rock with what
    # the shield lets through, not one of the pilot's moves comes too near a surface seen
    # or enters space never seen free.
    caster = hall_with_a_rock_beside(rock_x=-1.2)
    rig, pilot, shield = SensorRig(caster), GeometricPilot(), Shield()
    cfg = shield.config
    pose, executed = Pose(-2.1, 0.0, 0.0, 0.0), None
    for _ in range(12):
        observation = replace(rig.observe(pose), previous_action=executed)
        shield.observe(observation)
        action = pilot.decide(observation).action
        no_forward = cfg.rules.no_forward_within_m
        around = Surroundings.of(observation, shield.memory, cfg.body, cfg.margins, no_forward)
        judged = crawlway_move(
            action, around, body=cfg.body, margins=cfg.margins, no_forward_m=no_forward
        )
        hazard = move_hazard(
            action, around, body=cfg.body, margins=cfg.margins, crawlway=judged.crawlway
        )
        assert not hazard, f"{format_action(action)}: {hazard.text}"
        executed = shield.judge(action).action
        pose = kinematics.apply(pose, executed)


def test_with_the_same_room_either_side_its_5_degree_turns_go_the_same_way(monkeypatch) -> None:
    # Inside the standoff forward motion must come with a turn or a shift. Open water
    # with the ceiling and floor 1.5 m away: the shift would enter a side never seen, so
    # it turns 5 degrees instead; or, when the shift is judged safe but then refused,
    # it turns 5 degrees after all. Either way toward the roomier side, and with the same
    # room either side, the same way.
    view = synthetic(np.inf, d_top=1.5, d_bottom=1.5)
    instead_of_a_shift = GeometricPilot().decide(view).action
    monkeypatch.setattr(GeometricPilot, "_hazard", lambda *args: Hazard())
    monkeypatch.setattr(
        GeometricPilot, "_keep_clear", lambda self, action, *args: (replace(action, right=0.0), "")
    )
    after_a_refused_shift = GeometricPilot().decide(view).action
    assert instead_of_a_shift.forward > 0 and after_a_refused_shift.forward > 0
    assert abs(instead_of_a_shift.yaw_deg) == 5.0
    assert instead_of_a_shift.yaw_deg == after_a_refused_shift.yaw_deg


def test_boxed_in_it_searches_a_full_circle_then_backs_out() -> None:
    # Nothing new anywhere: it searches by turning one way; once it has turned all round
    # the place is a dead end, and it backs out (turning on, as no way back is in view).
    pilot = GeometricPilot()
    assert pilot.state.mode.name == "follow"
    modes = []
    for _ in range(10):
        pilot.decide(synthetic(1.0))
        modes.append(pilot.state.mode.name)
    assert modes == ["search"] * 8 + ["back out"] * 2
    pilot.reset()
    assert pilot.state.mode.name == "follow"


def test_at_a_fork_it_keeps_the_way_the_passage_has_led_not_the_bigger_looking_branch() -> None:
    # Maze seed 1007's junction: 33 m from the start, turned 25 degrees toward a side
    # passage, which fills the view; the main passage shows at the view's edge.
    pilot = GeometricPilot()
    pilot.map.position = np.array([33.0, 2.0, 0.0])
    pilot.map.heading = math.radians(25.0)
    side = _ViewOpening(bearing=6.0, elevation=-3.0, free_m=17.4, size=1781.0, visited=False,
                        tight=False)  # fmt: skip
    main = replace(side, bearing=-24.0, free_m=20.0, size=101.0)
    assert pilot._way_on([side, main]) is main
    # Two openings much the same way (either side of a boulder): the bigger one.
    beside = replace(main, bearing=-14.0, size=500.0)
    assert pilot._way_on([side, beside, main]) is beside
    assert pilot._way_on([side, main, beside]) is beside
    assert pilot._way_on([side]) is side
    # A crawlway is no fork of a passage the body fits with the full margin.
    assert pilot._way_on([side, replace(main, tight=True)]) is side
    # Near the start there is no way the passage has led yet: the biggest.
    pilot.map.position = np.array([2.0, 0.0, 0.0])
    assert pilot._way_on([side, main]) is side


def test_backing_out_it_tries_first_the_remembered_opening_that_leads_on() -> None:
    # 40 m from the start, facing back up a dead end: the opening nearest its heading is
    # a side passage across the way it came; the one that leads on lies behind it.
    pilot = GeometricPilot()
    pilot.map.position = np.array([40.0, 0.0, 0.0])
    pilot.map.heading = math.radians(180.0)
    across = Opening(bearing_deg=-60.0, free_m=12.0, visited=False, end=(40.0, 12.0, 0.0))
    on = Opening(bearing_deg=170.0, free_m=12.0, visited=False, end=(52.0, -2.0, 0.0))
    following = pilot.state
    backing_out = following.backing_out_of(pilot.map.position)
    assert pilot._in_order([across, on], backing_out) == [on, across]
    assert pilot._in_order([across, on], following) == [across, on]  # nearest the heading
