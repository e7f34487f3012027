"""The Gymnasium environment: the contract every driver relies on."""

from __future__ import annotations

from dataclasses import astuple, replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env, data_equivalence
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import cavenav  # noqa: F401 - registers cavenav/CaveNav-v0
from cavenav.core.errors import ActionError, ConfigError
from cavenav.core.types import Action, Observation, Pose
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.motion.kinematics import apply
from cavenav.pilots.geometric import GeometricPilot
from cavenav.pilots.random_pilot import RandomPilot
from cavenav.safety.shield import DepthMemory
from cavenav.sensors.depth import normalise_depth
from cavenav.sensors.rig import SensorConfig
from cavenav.sim.env import CaveNavEnv, Timings, snap_action
from cavenav.world.scenarios import Scenario, load_scenario
from tests.conftest import Overshooting

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_check_env_passes_for_s1() -> None:
    check_env(gym.make("cavenav/CaveNav-v0", scenario="S1", render_mode="rgb_array").unwrapped)


def test_check_env_passes_for_a_scenario_file_and_for_action_vectors() -> None:
    check_env(CaveNavEnv(EXAMPLES / "osrf_cave_straight.toml", action_format="vector"))


def test_gymnasium_make_needs_nothing_but_import_cavenav() -> None:
    env = gym.make("cavenav/CaveNav-v0", scenario="S4")
    assert env.spec is not None and env.spec.max_episode_steps == 150
    obs, info = env.reset(seed=0)
    assert obs["rgb"].shape == (480, 640, 3) and obs["depth"].dtype == np.uint8
    assert obs["depth"].shape == obs["depth_m"].shape == (480, 640, 1)  # a channel axis
    assert obs["depth_m"].max() <= 20.0 and obs["d_top"].shape == obs["d_bottom"].shape == (1,)
    assert info["scenario"] == "S4" and info["collision"] is False


def test_a_family_flown_by_name_gets_the_guideline_asked_for() -> None:
    """`guideline` lays the line in every cave flown, as --guideline does; the caves shared
    between environments keep none."""
    shared: dict = {}
    lined = CaveNavEnv("S1", guideline="yellow", resolution=(64, 48), caves=shared)
    plain = CaveNavEnv("S1", resolution=(64, 48), caves=shared)
    lined.reset(seed=0)
    plain.reset(seed=0)
    assert lined.scenario.guideline is not None and lined.scenario.guideline.colour == "yellow"
    assert plain.scenario.guideline is None
    assert lined.scenario.mesh is plain.scenario.mesh  # the same rock
    with pytest.raises(ConfigError, match="choose one of white, yellow"):
        CaveNavEnv("S1", guideline="red")


def test_a_vector_of_two_environments_steps() -> None:
    envs = gym.vector.SyncVectorEnv([lambda: CaveNavEnv("S1") for _ in range(2)])
    obs, _ = envs.reset(seed=[1, 2])
    assert obs["rgb"].shape == (2, 480, 640, 3)
    obs, reward, terminated, truncated, info = envs.step(("forward 1 m", "turn left 15 deg"))
    assert reward[0] == pytest.approx(1.0, abs=0.05) and reward[1] == pytest.approx(0.0, abs=1e-6)
    assert not terminated.any() and not truncated.any()
    envs.close()


def test_the_same_seed_and_actions_give_the_same_observations_bit_for_bit() -> None:
    actions = ["forward 1 m, turn left 10 deg", "ascend 0.3 m, strafe right 0.2 m", "forward 0.5 m"]

    def fly(seed: int) -> list[dict[str, np.ndarray]]:
        env = CaveNavEnv("S1")
        frames = [env.reset(seed=seed)[0]]
        frames += [env.step(a)[0] for a in actions]
        return frames

    first, again, other = fly(7), fly(7), fly(8)
    for a, b, c in zip(first, again, other, strict=True):
        for key in a:
            assert np.array_equal(a[key], b[key]), key
        assert np.array_equal(a["depth_m"], c["depth_m"])  # same cave, same poses
        assert not np.array_equal(a["rgb"], c["rgb"])  # another draw of sensor noise


def test_an_inadmissible_action_holds_says_why_and_counts_toward_the_budget() -> None:
    env = gym.make("cavenav/CaveNav-v0", max_episode_steps=2)
    _, start = env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step("forward 0.3 m")
    assert "forward 0.3 m is not admissible" in info["invalid_action"]
    assert info["pose"] == start["pose"] and info["action"] == "hold" and reward == 0.0
    _, _, terminated, truncated, info = env.step("fly to the moon")
    assert info["invalid_action"] and truncated and not terminated


def test_a_collision_terminates_with_a_penalty_and_leaves_the_vehicle_where_it_was(
    room_scenario: Scenario,
) -> None:
    env = CaveNavEnv(room_scenario, collision_penalty=10.0)
    _, start = env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step("strafe right 1 m")
    _, reward, terminated, truncated, info = env.step("strafe right 1 m")  # wall at 2 m
    assert info["collision"] and terminated and not truncated and not info["exit"]
    assert reward == pytest.approx(-10.0)
    assert info["pose"]["x"] == pytest.approx(start["pose"]["x"] - 1.0)
    assert info["collision_pose"]["x"] == pytest.approx(start["pose"]["x"] - 2.0)
    with pytest.raises(gym.error.ResetNeeded):
        env.step("hold")


def test_reaching_the_exit_terminates_and_the_rewards_add_up_to_the_progress(
    room_scenario: Scenario,
) -> None:
    env = CaveNavEnv(room_scenario)
    env.reset(seed=0)
    total, terminated, info = 0.0, False, {}
    while not terminated:
        _, reward, terminated, _, info = env.step("forward 1 m")
        total += reward
    assert info["exit"] and not info["collision"]
    assert total == pytest.approx(14.0) == pytest.approx(info["progress_m"])


def test_info_carries_what_a_pilot_sees_where_the_vehicle_is_and_how_long_it_took() -> None:
    env = CaveNavEnv("S1", resolution=(64, 48))
    obs, info = env.reset(seed=0)
    seen = info["observation"]
    assert isinstance(seen, Observation) and np.array_equal(seen.rgb, obs["rgb"])
    assert seen.previous_action is None and info["timings"].physics_ms is None
    obs, _, _, _, info = env.step("forward 1 m, turn left 10 deg")
    seen, pose = info["observation"], info["vehicle_pose"]
    assert seen.step == 1 and np.array_equal(seen.depth_png, obs["depth"][..., 0])
    assert seen.previous_action == Action(forward=1.0, yaw_deg=10.0)  # the action executed
    assert pose == apply(env.scenario.start, Action(forward=1.0, yaw_deg=10.0))  # unrounded
    assert pose.to_dict() == info["pose"]
    assert info["timings"].physics_ms > 0 and info["timings"].sense_ms > 0


def test_timings_ms_keeps_the_last_reset_or_step_times_as_before_info_carried_them() -> None:
    env = CaveNavEnv("S1", resolution=(64, 48))
    assert env.timings_ms == {}  # nothing flown yet
    _, info = env.reset(seed=0)
    assert env.timings_ms == {"sense": info["timings"].sense_ms}
    info = env.step("forward 1 m")[-1]
    timings = info["timings"]
    assert env.timings_ms == {"physics": timings.physics_ms, "sense": timings.sense_ms}
    assert list(env.timings_ms) == ["physics", "sense"] and timings.physics_ms > 0


def test_two_runs_of_one_seed_give_equal_info_whatever_the_timings() -> None:
    """Gymnasium's determinism check compares ``info`` whole: the typed observation by
    its images, the timings not at all (the same step is the same step on any machine)."""

    def fly() -> dict:
        env = CaveNavEnv("S1", resolution=(64, 48))
        env.reset(seed=5)
        return env.step("forward 0.5 m")[-1]

    first, again = fly(), fly()
    assert data_equivalence(first, again, exact=True)
    assert Timings(1.0, 2.0) == Timings(30.0)
    darker = replace(first["observation"], rgb=first["observation"].rgb // 2)
    assert darker != first["observation"] and first["observation"] == again["observation"]


def test_the_termination_names_how_the_episode_ended(room_scenario: Scenario) -> None:
    env = CaveNavEnv(room_scenario)
    assert env.reset(seed=0)[1]["termination"] is None
    assert env.step("strafe right 1 m")[-1]["termination"] is None
    assert env.step("strafe right 1 m")[-1]["termination"] == "collision"  # wall at 2 m
    env.reset(seed=0)
    info: dict = {}
    while not info.get("exit"):
        info = env.step("forward 1 m")[-1]
    assert info["termination"] == "exit"


def test_a_motion_that_drifts_reports_it_in_info_and_the_kinematics_report_none(
    room_scenario: Scenario,
) -> None:
    env = CaveNavEnv(room_scenario, motion=Overshooting())
    _, start = env.reset(seed=0)
    *_, info = env.step("forward 1 m")
    assert info["drift_m"] == pytest.approx(0.1) and info["drift_deg"] == 0.0
    assert info["commanded_pose"]["y"] == pytest.approx(start["pose"]["y"] - 1.0)
    assert info["pose"]["y"] == pytest.approx(start["pose"]["y"] - 1.1)  # where it went
    plain = CaveNavEnv(room_scenario)
    plain.reset(seed=0)
    assert not {"drift_m", "drift_deg", "commanded_pose"} & set(plain.step("forward 1 m")[-1])


def test_reset_options_choose_the_cave_for_that_reset(room_scenario: Scenario) -> None:
    env = CaveNavEnv("S1")
    _, info = env.reset(seed=0, options={"scenario": room_scenario})
    assert info["scenario"] == "room"
    _, info = env.reset(seed=0)
    assert info["scenario"] == "S1" and info["cave_seed"] == 0
    with pytest.raises(ConfigError, match="unknown reset option"):
        env.reset(options={"difficulty": 3})


def test_stepping_before_reset_says_to_reset() -> None:
    with pytest.raises(gym.error.ResetNeeded, match="Call reset"):
        CaveNavEnv("S1").step("hold")


def test_the_rendered_frame_is_the_colour_observation() -> None:
    env = CaveNavEnv("S1", render_mode="rgb_array")
    obs, _ = env.reset(seed=3)
    frame = env.render()
    assert frame is not None and np.array_equal(frame, obs["rgb"]) and frame is not obs["rgb"]


@pytest.mark.parametrize(
    ("vector", "expected"),
    [
        ((0.4, -0.14, 0.0, 12.0), Action(0.5, -0.1, 0.0, 10.0)),
        ((0.04, 0.9, 0.049, -170.0), Action(0.0, 1.0, 0.0, -180.0)),
        ((-1.0, 0.0, 0.05, 0.0), Action(-1.0, 0.0, 0.1, 0.0)),  # 0.05 m: up to the minimum
        ((0.0, 0.0, -0.734, 33.0), Action(0.0, 0.0, -0.73, 30.0)),  # rounded to the cm
        ((0.0, 0.0, 2.0, 180.0), Action(0.0, 0.0, 2.0, 180.0)),
    ],
)
def test_action_vectors_snap_to_the_nearest_admissible_values(vector, expected) -> None:
    assert snap_action(np.array(vector, np.float32)) == expected


def test_a_vector_that_is_not_four_finite_numbers_is_rejected() -> None:
    with pytest.raises(ActionError, match="4 finite numbers"):
        snap_action(np.array([0.0, np.nan, 0.0, 0.0]))


class _CountsPrints(np.ndarray):
    """An action vector that counts how often it is printed."""

    printed = 0

    def __repr__(self) -> str:
        _CountsPrints.printed += 1
        return "printed"


def test_a_valid_vector_is_snapped_without_being_printed() -> None:
    """Its text is for the reason of a hold only: a step must not pay for it."""
    vector = np.array([0.4, 0.0, 0.0, 12.0]).view(_CountsPrints)
    assert snap_action(vector) == Action(0.5, 0.0, 0.0, 10.0)
    assert _CountsPrints.printed == 0
    with pytest.raises(ActionError, match="printed"):
        snap_action(np.array([0.4, np.nan, 0.0, 12.0]).view(_CountsPrints))


def test_a_huge_but_finite_vector_snaps_to_the_largest_magnitudes() -> None:
    """Not to a hold: beyond 1e17 every candidate is one float away from the value."""
    assert snap_action(np.array([1e40, -1e300, 1e40, -1e300])) == Action(1.0, -1.0, 2.0, -180.0)


# Whatever a policy or a script hands to step: numbers, text, containers, arrays of every
# dtype and shape, Actions holding anything, plain objects.
_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(), st.complex_numbers(),
    st.text(max_size=6), st.binary(max_size=6), st.decimals(), st.fractions(), st.builds(object),
)  # fmt: skip
_anything = st.recursive(
    _scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5),
        st.tuples(inner, inner, inner, inner),
        st.dictionaries(st.text(max_size=3), inner, max_size=3),
    ),
    max_leaves=12,
)
_actions = st.one_of(
    _anything,
    hnp.arrays(hnp.scalar_dtypes(), hnp.array_shapes(min_dims=0, max_dims=2, max_side=5)),
    st.lists(st.floats(-3, 3), min_size=4, max_size=4),  # near the admissible ones
    st.builds(Action, _anything, _anything, _anything, _anything),
)


@pytest.mark.parametrize("action_format", ["vector", "text"])
@given(action=_actions)
@example(action=Action(10**400, 0, 0, 0))  # beyond float's range: no OverflowError
@example(action=Action(True, 0, 0, 0))  # a flag is no magnitude, though True == 1
def test_every_action_whatever_its_type_is_admissible_or_a_hold_that_says_why(
    action_format: str, action: object
) -> None:
    env = CaveNavEnv("S1", action_format=action_format)  # no cave is built before reset
    command, why = env.command(action)
    if why is None:
        assert env.space.is_valid(command)
        assert all(type(part) is float for part in astuple(command)), command
    else:
        assert command == Action() and why


@pytest.mark.parametrize(
    "action",
    [
        np.array(["forward", "0", "0", "0"]),
        {"forward": 1.0},
        object(),
        np.zeros((2, 2)),
        [0.5, 0.0, 0.0],
        [np.nan, 0.0, 0.0, 0.0],
        [1j, 0, 0, 0],
        Action("1", 0.0, 0.0, 0.0),  # type: ignore[arg-type]
        Action(10**400, 0.0, 0.0, 0.0),
        Action(True, 0.0, 0.0, 0.0),
    ],
    ids=[
        "text",
        "dict",
        "object",
        "shape 2x2",
        "three",
        "nan",
        "complex",
        "an Action of text",
        "an Action of a huge int",
        "an Action of a bool",
    ],  # fmt: skip
)
def test_a_vector_environment_holds_on_a_bad_action_and_says_why(action: object) -> None:
    env = CaveNavEnv("S1", action_format="vector", resolution=(32, 32))
    _, before = env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step(action)
    assert info["invalid_action"] and info["action"] == "hold"
    assert info["pose"] == before["pose"] and reward == 0.0
    assert not terminated and not truncated


# ------------------------------------------------------------------ resolution


def test_the_resolution_keyword_sizes_the_observations_and_check_env_passes_at_84x84() -> None:
    env = gym.make(
        "cavenav/CaveNav-v0", scenario="S1", resolution=(84, 84), render_mode="rgb_array"
    )
    space = env.observation_space
    assert space["rgb"].shape == (84, 84, 3)
    assert space["depth"].shape == space["depth_m"].shape == (84, 84, 1)
    check_env(env.unwrapped)
    obs, _ = env.reset(seed=0)
    frame = env.render()
    assert obs["rgb"].shape == (84, 84, 3) and frame is not None and frame.shape == (84, 84, 3)
    assert env.unwrapped.observation.hfov_deg == pytest.approx(53.13, abs=0.01)


def test_sensors_set_the_resolution_too_and_the_resolution_keyword_wins() -> None:
    sensors = SensorConfig(sounder="beam").with_resolution(160, 120)
    assert CaveNavEnv("S1", sensors=sensors).observation_space["depth"].shape == (120, 160, 1)
    both = CaveNavEnv("S1", sensors=sensors, resolution=(84, 84))
    assert both.observation_space["depth"].shape == (84, 84, 1) and both.sensors.sounder == "beam"
    assert CaveNavEnv("S1").observation_space["depth"].shape == (480, 640, 1)  # the paper's


@pytest.mark.parametrize("resolution", [(84, 0), (84.0, 84), "84x84"])
def test_a_bad_resolution_is_refused_when_the_environment_is_made(resolution) -> None:
    with pytest.raises(ConfigError, match="resolution"):
        CaveNavEnv("S1", resolution=resolution)


def test_a_vector_of_two_84x84_environments_steps_with_action_vectors() -> None:
    envs = gym.vector.SyncVectorEnv(
        [lambda: CaveNavEnv("S1", resolution=(84, 84), action_format="vector") for _ in range(2)]
    )
    obs, _ = envs.reset(seed=[1, 2])
    assert obs["rgb"].shape == (2, 84, 84, 3) and obs["depth_m"].shape == (2, 84, 84, 1)
    obs, reward, *_ = envs.step(np.array([[1.0, 0, 0, 0], [0, 0, 0, 15.0]], np.float32))
    assert reward[0] == pytest.approx(1.0, abs=0.05) and reward[1] == pytest.approx(0.0, abs=1e-6)
    envs.close()


def _seen_at(width: int, height: int, depth_m: float) -> Observation:
    depth = np.full((height, width), depth_m, np.float32)
    return Observation(
        rgb=np.zeros((height, width, 3), np.uint8),
        depth_m=depth,
        depth_png=normalise_depth(depth),
        d_top=3.0,
        d_bottom=3.0,
        depth_range=(0.0, 20.0),
        hfov_deg=53.13,
        camera_offset_m=0.2,
    )


@pytest.mark.parametrize(("size", "blocks"), [((640, 480), (48, 64)), ((84, 84), (84, 84))])
def test_the_depth_memory_keeps_about_64_columns_of_free_space_at_any_resolution(
    size: tuple[int, int], blocks: tuple[int, int]
) -> None:
    memory = DepthMemory()
    memory.update(_seen_at(*size, 5.0), None)
    (frame,) = memory.frames
    assert frame.depth.shape == blocks  # 10 x 10 pixels a block at 640x480, as always
    assert frame.depth == pytest.approx(5.0, abs=0.05)
    # The wall 5 m ahead is known free up to 4.6 m across the whole view, edges included.
    across = np.linspace(-2.4, 2.4, 9)
    points = np.stack([np.full(9, 4.9), across, np.zeros(9)], axis=1)
    assert memory.seen_free(points, margin_m=0.3).all()
    assert not memory.seen_free(points + (0.3, 0, 0), margin_m=0.3).any()


@pytest.mark.slow
def test_the_shield_keeps_the_random_pilot_off_the_walls_at_84x84(room_scenario: Scenario) -> None:
    sensors = SensorConfig().with_resolution(84, 84)
    config = EpisodeConfig(
        max_steps=60, save_frames=False, plots=False, shield=True, sensors=sensors
    )
    result = run_episode(room_scenario, RandomPilot(seed=3), config)
    assert result.summary["collisions"] == 0 and result.termination != "collision"
    assert result.summary["shield_interventions"] > 0


@pytest.mark.slow
def test_the_geometric_pilot_reaches_the_exit_of_s1_at_160x120_without_touching_a_wall() -> None:
    sensors = SensorConfig().with_resolution(160, 120)
    config = EpisodeConfig(sensors=sensors, save_frames=False, plots=False)
    result = run_episode(load_scenario("S1", 0), GeometricPilot(), config)
    assert result.termination == "exit" and result.summary["collisions"] == 0
    assert result.summary["config"]["sensors"]["camera"]["width"] == 160


def test_a_motion_written_before_motions_reported_drift_is_measured_against_the_kinematics():
    """A user's Motion with only ``start`` and ``move`` (the protocol before `drift`)
    still flies, and the environment reports how far it drifted from the command."""

    class HalfwayForward:
        def start(self, pose: Pose) -> Pose:
            return pose

        def move(self, pose: Pose, action: Action) -> Pose:
            return apply(pose, replace(action, forward=action.forward / 2))

    env = CaveNavEnv("S1", resolution=(32, 24), motion=HalfwayForward())
    env.reset(seed=0)
    *_, info = env.step("forward 1 m")
    assert info["drift_m"] == pytest.approx(0.5)
    assert info["drift_deg"] == pytest.approx(0.0)
