"""Water that flows through the cave and carries the vehicle, and what moves cost a
BlueROV2's battery."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cavenav.core.errors import ConfigError
from cavenav.core.types import Action, Cruise, Pose
from cavenav.motion.energy import BATTERY_WH, T200, PowerModel, lamp_watts
from cavenav.motion.kinematics import apply, carried
from cavenav.pilots.prompt import PromptConfig, render_system
from cavenav.pilots.vlm import EncodedObservation, build_messages
from cavenav.sim.env import CaveNavEnv
from cavenav.world.current import Current, CurrentField, carry
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import Scenario
from tests.conftest import Overshooting

SMALL = (32, 24)  # the images do not matter here
ROOM_SECTION_M2 = 16.0  # the test corridor is 4 m by 4 m across


def corridor_env(room_scenario: Scenario, **options: object) -> CaveNavEnv:
    env = CaveNavEnv(room_scenario, resolution=SMALL, **options)
    env.reset(seed=0)
    return env


ALONG_THE_CORRIDOR = np.array([[0.0, 9.0, 0.0], [0.0, -9.0, 0.0]])  # start to exit


def with_centre_line(room_scenario: Scenario) -> Scenario:
    return replace(room_scenario, centreline=ALONG_THE_CORRIDOR)


# ------------------------------------------------------------------ the current


def test_still_water_moves_the_vehicle_exactly_as_the_spec_says(room_scenario: Scenario) -> None:
    for current in (None, Current(0.0, gusts=1.0)):
        env = corridor_env(room_scenario, current=current)
        start = env.pose
        _, _, _, _, info = env.step("forward 1 m, turn left 15 deg")
        assert info["vehicle_pose"] == apply(start, Action(forward=1.0, yaw_deg=15))
        assert "drift_m" not in info and info["current_m_s"] is None


def test_the_cross_section_is_measured_on_the_cave(room_scenario: Scenario) -> None:
    field = CurrentField.measure(
        RayCaster(room_scenario.mesh), ALONG_THE_CORRIDOR, Current(1.6), seed=0
    )
    inner = field.areas[4:-4]  # away from the end walls
    assert inner == pytest.approx(ROOM_SECTION_M2, rel=0.01)
    assert field.speeds[4:-4] == pytest.approx(1.6 / ROOM_SECTION_M2, rel=0.01)


def test_water_runs_faster_where_the_passage_narrows() -> None:
    from cavenav.world.mesh import make_mesh

    wide = RayCaster(make_mesh(*_box((4.0, 20.0, 4.0)), "wide"))
    narrow = RayCaster(make_mesh(*_box((2.0, 20.0, 2.0)), "narrow"))
    speeds = [
        float(np.median(CurrentField.measure(c, ALONG_THE_CORRIDOR, Current(2.0), 0).speeds))
        for c in (wide, narrow)
    ]
    assert speeds[1] / speeds[0] == pytest.approx(4.0, rel=0.02)  # continuity: Q / A


def _box(extents: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    box = trimesh.creation.box(extents=extents)
    return box.vertices, box.faces


def test_a_spring_pushes_the_vehicle_back_by_the_water_speed_times_the_move(
    room_scenario: Scenario,
) -> None:
    env = corridor_env(with_centre_line(room_scenario), current=Current(1.6, gusts=0.0))
    start = env.pose
    _, _, _, _, info = env.step("forward 1 m")  # 2 s at 0.5 m/s, against 0.1 m/s
    commanded = apply(start, Action(forward=1.0))
    assert info["commanded_pose"] == commanded.to_dict()
    assert info["vehicle_pose"].y - commanded.y == pytest.approx(0.2, rel=0.02)
    assert info["vehicle_pose"].x == pytest.approx(commanded.x, abs=1e-9)
    assert info["drift_m"] == pytest.approx(0.2, rel=0.02)
    assert info["current_m_s"] == pytest.approx(0.1, rel=0.02)


def test_a_negative_discharge_carries_the_vehicle_toward_the_exit(
    room_scenario: Scenario,
) -> None:
    env = corridor_env(with_centre_line(room_scenario), current=Current(-1.6, gusts=0.0))
    start = env.pose
    _, _, _, _, info = env.step("turn left 90 deg")  # 3 s of turning, carried all along
    assert info["vehicle_pose"].y - start.y == pytest.approx(-0.3, rel=0.02)


def test_without_a_centre_line_the_water_follows_the_shortest_way_through(
    room_scenario: Scenario,
) -> None:
    assert room_scenario.centreline is None
    env = corridor_env(room_scenario, current=Current(1.6, gusts=0.0))
    _, _, _, _, info = env.step("forward 1 m")
    assert info["current_m_s"] == pytest.approx(0.1, rel=0.02)
    assert info["drift_m"] == pytest.approx(0.2, rel=0.02)


def test_gusts_vary_in_time_and_hold_the_depth(room_scenario: Scenario) -> None:
    field = CurrentField.measure(
        RayCaster(room_scenario.mesh), ALONG_THE_CORRIDOR, Current(3.2, gusts=0.5), seed=0
    )
    here = room_scenario.start.position
    speeds = [np.linalg.norm(field.velocity(here, t)) for t in np.arange(0.0, 120.0, 5.0)]
    assert np.std(speeds) / np.mean(speeds) > 0.15
    assert any(abs(field.velocity(here, t)[2]) > 0.01 for t in np.arange(0.0, 120.0, 5.0))
    env = corridor_env(room_scenario, current=Current(3.2, gusts=0.5))
    for _ in range(5):
        before = env.pose
        _, _, _, _, info = env.step("forward 0.5 m")
        assert info["vehicle_pose"].z == pytest.approx(before.z, abs=1e-12)  # depth hold


@pytest.mark.parametrize("discharge", [3.2, -3.2])
def test_a_gust_travels_downstream_with_the_flow(room_scenario: Scenario, discharge: float) -> None:
    field = CurrentField.measure(
        RayCaster(room_scenario.mesh), ALONG_THE_CORRIDOR, Current(discharge, gusts=0.5), seed=0
    )
    nearer_start, nearer_exit = np.array([0.0, 4.0, 0.0]), np.array([0.0, -2.0, 0.0])
    upstream, downstream = (
        (nearer_exit, nearer_start) if discharge > 0 else (nearer_start, nearer_exit)
    )
    later = 6.0 / (abs(discharge) / ROOM_SECTION_M2)  # 6 m at the flow's speed
    for t in (0.0, 7.0, 30.0):
        assert np.linalg.norm(field.velocity(downstream, t + later)) == pytest.approx(
            np.linalg.norm(field.velocity(upstream, t)), rel=0.03
        )


def test_the_same_seed_flies_the_same_water_and_another_seed_other_gusts(
    room_scenario: Scenario,
) -> None:
    def flight(seed: int) -> list[Pose]:
        env = CaveNavEnv(room_scenario, resolution=SMALL, current=Current(3.2, gusts=0.5))
        env.reset(seed=seed)
        return [env.step("forward 1 m")[4]["vehicle_pose"] for _ in range(4)]

    assert flight(1) == flight(1)
    assert flight(1) != flight(2)


def test_a_vehicle_over_mavlink_meets_its_own_water(room_scenario: Scenario) -> None:
    with pytest.raises(ConfigError, match="meets its own"):
        CaveNavEnv(room_scenario, motion=Overshooting(), current=Current(1.0))


@pytest.mark.parametrize(
    ("discharge", "gusts"), [(math.inf, 0.2), (1e300, 0.2), (-1.1e4, 0.2), (1.0, -0.1), (1.0, 1.5)]
)
def test_a_current_that_cannot_be_is_refused(discharge: float, gusts: float) -> None:
    with pytest.raises(ConfigError):
        Current(discharge, gusts)


def water_file(tmp_path, table: str) -> str:
    from tests.conftest import write_room

    path = write_room(tmp_path)
    path.write_text(path.read_text() + f"[water]\n{table}\n")
    return str(path)


def test_a_scenario_files_water_flows_unless_the_episode_says_otherwise(tmp_path) -> None:
    from cavenav.episode.settings import EpisodeConfig
    from cavenav.world.scenarios import load_scenario

    cave = load_scenario(
        water_file(tmp_path, "discharge_m3s = 2\ngusts = 0.1"), 0
    )  # an integer is a number
    assert cave.water == {"discharge_m3s": 2.0, "gusts": 0.1}
    assert EpisodeConfig().for_episode(cave).current == Current(2.0, 0.1)
    assert EpisodeConfig(discharge_m3s=0.0).current_for(cave).still  # --discharge 0
    assert EpisodeConfig(gusts=0.5).current_for(cave) == Current(2.0, 0.5)
    still = load_scenario(water_file(tmp_path / "still", ""), 0)
    assert EpisodeConfig().current_for(still) == Current()  # SPEC section 5


@pytest.mark.parametrize(
    ("table", "field"),
    [("discharge_m3s = 1e9", "water.discharge_m3s"), ("gusts = 2", "water.gusts"),
     ("speed = 1", "water.speed"), ("discharge_m3s = true", "water.discharge_m3s"),
     ("gusts = false", "water.gusts")],
)  # fmt: skip
def test_a_water_table_that_cannot_be_is_refused_by_field(tmp_path, table: str, field: str) -> None:
    from cavenav.world.scenarios import load_scenario

    with pytest.raises(ConfigError, match=field.replace(".", r"\.")) as refused:
        load_scenario(water_file(tmp_path, table), 0)
    assert "\n" not in str(refused.value)


# ------------------------------------------------------------------ the energy


def test_at_top_speed_the_four_vectored_thrusters_run_at_full_throttle() -> None:
    power = PowerModel().thrust_power_w(np.array([[1.5, 0.0, 0.0]]))
    assert power[0] == pytest.approx(4 * T200.max_power_w)


def test_a_t200_draws_as_thrust_to_the_power_one_and_a_half() -> None:
    full = T200.max_thrust_n
    assert T200.power_w(np.array([full, full / 4, -full / 4, 2 * full])) == pytest.approx(
        T200.max_power_w * np.array([1.0, 0.125, 0.125, 1.0])
    )


def test_moving_costs_more_the_faster_and_sideways_more_than_ahead() -> None:
    power = PowerModel().thrust_power_w(
        np.array([[0.25, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]])
    )
    ahead_slow, ahead, sideways, up = power
    assert ahead == pytest.approx(8 * ahead_slow)  # drag v^2, power thrust^1.5
    assert ahead < sideways < up  # the body shows the flow a larger face


def test_a_hold_costs_nothing_a_turn_the_electronics_and_a_move_its_thrust_too(
    room_scenario: Scenario,
) -> None:
    env = corridor_env(room_scenario)
    hotel_w = env.power.hotel_w + lamp_watts(2, 1500.0)
    energies = [env.step(action)[4]["step_energy_wh"] for action in ("hold", "turn left 30 deg")]
    assert energies == pytest.approx([0.0, hotel_w * 1.0 / 3600])
    _, _, _, _, info = env.step("forward 1 m")
    thrust_w = float(env.power.thrust_power_w(np.array([[0.5, 0.0, 0.0]]))[0])
    assert info["step_energy_wh"] == pytest.approx((thrust_w + hotel_w) * 2.0 / 3600)
    assert info["energy_left_wh"] == pytest.approx(
        BATTERY_WH - sum(energies) - info["step_energy_wh"]
    )
    assert info["observation"].energy_left_wh == info["energy_left_wh"]


def test_lamps_switched_off_draw_nothing(room_scenario: Scenario) -> None:
    from cavenav.sensors.rig import SensorConfig

    lamps_off = SensorConfig().with_optics({"light_power": 0.0})
    env = CaveNavEnv(room_scenario, resolution=SMALL, sensors=lamps_off)
    assert env.power.lamps_w == 0.0
    assert CaveNavEnv(room_scenario, resolution=SMALL).power.lamps_w == 30.0


def test_holding_depth_against_the_waters_rise_and_fall_costs_energy(
    room_scenario: Scenario,
) -> None:
    field = CurrentField.measure(
        RayCaster(room_scenario.mesh), ALONG_THE_CORRIDOR, Current(6.4, gusts=1.0), seed=3
    )
    move, start = Action(forward=1.0), room_scenario.start
    moved = apply(start, move)
    still = carry(None, start, move, moved, 10.0, Cruise())
    flowing = carry(field, start, move, moved, 10.0, Cruise())
    assert still.carried_m == (0.0, 0.0) and flowing.carried_m != (0.0, 0.0)
    assert carried(moved, flowing.carried_m).z == moved.z  # the depth is held
    vertical = flowing.through_water[:, 2]
    assert np.abs(vertical).max() > 0.01  # the thrusters push against the water's own
    model = PowerModel()
    assert model.energy_wh(flowing.dt, flowing.through_water) > model.energy_wh(
        still.dt, still.through_water
    )


def test_an_energy_budget_ends_the_episode_as_battery(room_scenario: Scenario) -> None:
    env = corridor_env(room_scenario, battery_wh=0.12)
    endings = [env.step("forward 0.5 m")[2:5:2] for _ in range(5)]
    terminated = [done for done, _ in endings]
    assert terminated == [False, False, False, False, True]  # 0.0263 Wh a step
    info = endings[-1][1]
    assert info["termination"] == "battery" and not info["exit"]
    assert info["energy_used_wh"] >= 0.12 > info["energy_used_wh"] - info["step_energy_wh"]


# ------------------------------------------------------------------ the prompt


def test_energy_aware_prompting_tells_the_model_its_battery_and_only_when_asked() -> None:
    seen = EncodedObservation("data:image/png;base64,AA", "data:image/png;base64,AA", 2.0, 3.0)
    told = build_messages("system", seen, [], energy_left_wh=12.345)
    assert {"type": "text", "text": "Battery: 12.35 Wh left."} in told[1]["content"]
    plain = build_messages("system", seen, [])
    assert not any("Battery" in part.get("text", "") for part in plain[1]["content"])
    assert "# Your battery" in render_system(PromptConfig(energy=True))
    assert "battery" not in render_system(PromptConfig()).lower()
