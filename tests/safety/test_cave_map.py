"""The pilot's map: built from observations and executed actions only, never the mesh."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cavenav.core.types import Action, Pose
from cavenav.motion.kinematics import apply
from cavenav.safety.cave_map import FREE, OCCUPIED, UNKNOWN, CaveMap
from cavenav.sensors.rig import SensorRig
from cavenav.world.raycast import RayCaster
from tests.conftest import box_room

# A corridor 6 m wide, 40 m long and 5 m high along y; heading -y is psi = 0.
CORRIDOR = (6.0, 40.0, 5.0)


def fly(actions: list[Action], corridor: tuple = CORRIDOR) -> tuple[CaveMap, Pose]:
    """Fly ``actions`` down the corridor from 15 m before its middle, mapping every
    observation; the map and the pose reached."""
    rig = SensorRig(RayCaster(box_room(extents=corridor)))
    cave_map, pose, previous = CaveMap(), Pose(0.0, 15.0, 0.0, 0.0), None
    for action in [*actions, None]:
        observation = rig.observe(pose)
        cave_map.update(observation, previous)
        if action is not None:
            pose, previous = apply(pose, action), action
    return cave_map, pose


def test_dead_reckoning_follows_the_pose_update_of_the_spec() -> None:
    actions = [Action(forward=1.0, yaw_deg=30), Action(right=0.5, up=0.3), Action(yaw_deg=-90)]
    cave_map, pose = CaveMap(), Pose(0.0, 0.0, 0.0, 0.0)
    for action in actions:
        cave_map.move(action)
        pose = apply(pose, action)
    # The map frame is the start's body frame: x its heading (-y), y its left (+x), z up.
    expected = np.array([-pose.position[1], pose.position[0], pose.position[2]])
    assert cave_map.position == pytest.approx(expected, abs=1e-9)
    assert math.degrees(cave_map.heading) == pytest.approx(-60.0)
    assert cave_map.travelled_m == pytest.approx(1.0 + math.hypot(0.5, 0.3))


def test_what_the_camera_saw_is_free_up_to_the_wall_and_unknown_behind_it() -> None:
    cave_map, _ = fly([])
    # The corridor's far wall is 35 m ahead, beyond the map's range: free as far as it saw.
    ahead = np.array([[3.0, 0.0, 0.0], [12.0, 0.0, 0.0]])
    assert (cave_map.state(ahead) == FREE).all()
    # Its side walls 3 m to either side, 10 m ahead, are surfaces; beyond them, rock unseen.
    assert cave_map.state(np.array([[10.0, 3.1, 0.0], [10.0, -3.1, 0.0]])).tolist() == [
        OCCUPIED,
        OCCUPIED,
    ]
    assert cave_map.state(np.array([[10.0, 5.0, 0.0]]))[0] == UNKNOWN
    assert cave_map.state(np.array([[-6.0, 0.0, 0.0]]))[0] == UNKNOWN  # behind, never seen


def test_the_path_flown_is_visited_and_the_way_on_is_not() -> None:
    cave_map, _ = fly([Action(forward=1.0)] * 8)
    start, ahead = np.array([[0.0, 0.0, 0.0]]), cave_map.to_map(np.array([[6.0, 0.0, 0.0]]))
    assert cave_map.visited(start)[0]
    assert not cave_map.visited(ahead)[0]
    # The last few metres are where the vehicle is, not where it has been.
    assert not cave_map.visited(cave_map.position[None])[0]


def test_openings_tell_the_way_back_from_the_way_on() -> None:
    cave_map, _ = fly([Action(forward=1.0)] * 8 + [Action(yaw_deg=90)])  # now facing a wall
    openings = {round(o.bearing_deg): o for o in cave_map.openings()}
    way_on, way_back = openings[-90], openings[90]  # the passage ran ahead: now to the right
    assert not way_on.visited and way_back.visited
    assert not any(abs(b) < 30 for b in openings)  # the side wall 3 m ahead is no opening


def blue(image: np.ndarray) -> np.ndarray:
    """Pixels a reader calls blue (the vehicle), whatever the exact shade."""
    channels = image.astype(int)
    return channels[..., 2] - channels[..., :2].max(axis=-1) > 80


def reddish(image: np.ndarray) -> np.ndarray:
    """Pixels a reader calls red (the path flown), whatever the exact shade."""
    channels = image.astype(int)
    return channels[..., 0] - channels[..., 1:].max(axis=-1) > 100


def test_the_top_down_picture_shows_free_space_walls_and_the_vehicle() -> None:
    cave_map, _ = fly([Action(forward=1.0)] * 4)
    image = cave_map.top_down(pixels=128, span_m=32.0)
    assert image.shape == (128, 128, 3) and image.dtype == np.uint8
    centre = 64
    above = image[centre - 30, centre]  # 7.5 m ahead, mid-corridor: seen free, light
    assert above.min() > 200
    beside = image[centre - 30, centre + 10 : centre + 15]  # about 3 m to the right: the wall
    assert beside.max(axis=1).min() < 80
    assert blue(image[centre - 4 : centre, centre - 1 : centre + 2]).any()  # the vehicle
    assert "Flown 4.0 m" in cave_map.describe()


def test_a_low_ceiling_is_no_wall_and_the_path_behind_stays_behind() -> None:
    # 2.4 m high: the ceiling and floor lie inside the picture's band of +-1.5 m.
    cave_map, _ = fly([Action(forward=1.0)] * 18 + [Action(yaw_deg=180)], (6.0, 40.0, 2.4))
    image = cave_map.top_down(pixels=128, span_m=32.0)
    centre = 64
    assert image[centre + 20, centre].min() > 200  # 5 m behind, the way it came: free
    red = reddish(image)
    rows = np.flatnonzero(red.any(axis=1))
    # The path runs from the vehicle ahead (the way back) off the picture's top edge, and
    # nowhere else: no stripes from points beyond the edge.
    assert rows.max() <= centre + 2 and red[:, : centre - 8].sum() == 0
