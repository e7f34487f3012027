"""Swept collision of the vehicle's body along the whole move (SPEC section 2)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from cavenav.core.types import Action, Pose
from cavenav.motion.kinematics import apply
from cavenav.world.collision import VehicleBody, swept_collision
from cavenav.world.mesh import make_mesh
from cavenav.world.raycast import RayCaster
from tests.conftest import box_room

BODY = VehicleBody()


def thin_wall(y: float = -1.0) -> RayCaster:
    """A zero-thickness 10 x 10 m wall across the y axis at ``y``."""
    v = np.array([[-5, y, -5], [5, y, -5], [5, y, 5], [-5, y, 5]], float)
    return RayCaster(make_mesh(v, np.array([[0, 1, 2], [0, 2, 3]])))


def test_a_move_through_a_thin_wall_is_a_collision() -> None:
    start = Pose(0, 0, 0, 0)
    end = apply(start, Action(forward=1.0))
    assert swept_collision(thin_wall(-0.5), BODY, start, end)


def test_the_end_pose_alone_would_miss_it() -> None:
    # A 2 m move across a wall: both end poses are clear, the path is not.
    start, end = Pose(0, 0, 0, 0), Pose(0, -2.0, 0, 0)
    caster = thin_wall(-1.0)
    assert caster.distance(start.position[None])[0] > BODY.bounding_radius
    assert caster.distance(end.position[None])[0] > BODY.bounding_radius
    assert swept_collision(caster, BODY, start, end)


def test_the_body_size_counts_not_just_the_centre() -> None:
    # The nose (0.23 m ahead of the centre) reaches the wall before the centre does.
    start = Pose(0, 0, 0, 0)
    assert swept_collision(thin_wall(-0.4), BODY, start, Pose(0, -0.2, 0, 0))
    assert not swept_collision(thin_wall(-0.6), BODY, start, Pose(0, -0.2, 0, 0))


def test_moving_along_a_wall_is_no_collision() -> None:
    caster = RayCaster(box_room())  # side walls at x = +-2
    start = Pose(1.4, 5.0, 0, 0)
    assert not swept_collision(caster, BODY, start, Pose(1.4, -5.0, 0, 0))


def test_turning_in_place_sweeps_the_long_body() -> None:
    # Heading along a corridor 0.5 m wide: turning 90 degrees swings the 0.46 m long body
    # into the side walls, while the 0.34 m wide body fits going straight.
    caster = RayCaster(box_room(extents=(0.5, 20.0, 4.0)))
    start = Pose(0, 0, 0, 0)
    assert not swept_collision(caster, BODY, start, Pose(0, -1.0, 0, 0))
    assert swept_collision(caster, BODY, start, Pose(0, 0, 0, math.pi / 2))


@pytest.mark.parametrize("dz", [1.5, -1.5])
def test_vertical_moves_hit_ceiling_and_floor(dz: float) -> None:
    caster = RayCaster(box_room(extents=(4, 20, 2)))  # ceiling and floor at z = +-1
    start = Pose(0, 0, 0, 0)
    assert swept_collision(caster, BODY, start, apply(start, Action(up=dz)))


def test_open3d_is_imported_without_its_web_viewer_which_still_works_when_called() -> None:
    # In a fresh process: Dash and Plotly cost 0.75 s of every start-up otherwise. A ray
    # caster built for a mesh is what loads Open3D for cavenav.
    script = (
        "import sys\n"
        "import numpy as np\n"
        "from cavenav.world.mesh import make_mesh\n"
        "from cavenav.world.raycast import RayCaster\n"
        "v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)\n"
        "RayCaster(make_mesh(v, np.array([[0, 1, 2]])))\n"
        "assert 'dash' not in sys.modules and 'plotly' not in sys.modules\n"
        "import open3d as o3d\n"
        "figure = o3d.visualization.get_plotly_fig([o3d.geometry.TriangleMesh.create_box()])\n"
        "print(type(figure).__module__, 'dash' in sys.modules)\n"
        # Importing the real viewer binds the submodule on its package under the name
        # of the function the package had taken from it; the functions must stay.
        "assert callable(o3d.visualization.draw_plotly), o3d.visualization.draw_plotly\n"
        "assert callable(o3d.visualization.get_plotly_fig), o3d.visualization.get_plotly_fig\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["plotly.graph_objs._figure", "True"]
