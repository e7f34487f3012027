"""Contact sheets: what a cave looks like to the vehicle, before anyone flies it.

The poses come from a flight of the geometric pilot (which needs only depth), spaced
evenly by distance along its path from the start to the last pose before the exit, so
any mesh with a start and an exit gets a sheet. Each cell shows the colour view a VLM
would receive beside its depth PNG.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: never open a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.backend_bases import FigureCanvasBase  # noqa: E402

from cavenav.core.errors import ConfigError  # noqa: E402
from cavenav.core.files import cannot_write, save_figure  # noqa: E402
from cavenav.core.types import Pose  # noqa: E402
from cavenav.episode.loop import run_episode  # noqa: E402
from cavenav.episode.settings import EpisodeConfig  # noqa: E402
from cavenav.pilots.geometric import GeometricPilot  # noqa: E402
from cavenav.sensors.rig import SensorConfig, SensorRig  # noqa: E402
from cavenav.world.procedural import arc_length  # noqa: E402
from cavenav.world.raycast import RayCaster  # noqa: E402
from cavenav.world.scenarios import Scenario  # noqa: E402

__all__ = ["GalleryView", "passage_poses", "render_views", "write_contact_sheet"]


@dataclass(frozen=True)
class GalleryView:
    """One rendered pose of a contact sheet."""

    pose: Pose
    distance_m: float  # along the path from the start
    rgb: np.ndarray
    depth_png: np.ndarray
    d_top: float
    d_bottom: float


def passage_poses(
    scenario: Scenario, count: int = 6, max_steps: int | None = None, before_exit_m: float = 7.0
) -> list[tuple[Pose, float]]:
    """``count`` poses evenly spaced along the geometric pilot's path, with their distances.

    The path stops ``before_exit_m`` short of the exit, so the last view frames the opening;
    it gets ``max_steps`` steps, by default the scenario's budget.
    """
    flight = run_episode(
        scenario,
        GeometricPilot(),
        EpisodeConfig(max_steps=max_steps, plots=False, stuck_after=None),
    )
    inside = [p for p in flight.poses if scenario.exit_distance(p.position) > before_exit_m]
    poses = inside or flight.poses[:1]
    xyz = np.array([p.position for p in poses])
    along = arc_length(xyz)
    targets = np.linspace(0.0, along[-1], count)
    picks = sorted({int(np.argmin(np.abs(along - t))) for t in targets})
    return [(poses[k], float(along[k])) for k in picks]


def render_views(
    scenario: Scenario, sensors: SensorConfig, poses: list[tuple[Pose, float]]
) -> list[GalleryView]:
    rig = SensorRig(RayCaster(scenario.mesh), sensors, scenario.guideline)
    views = []
    for pose, distance in poses:
        obs = rig.observe(pose)
        views.append(GalleryView(pose, distance, obs.rgb, obs.depth_png, obs.d_top, obs.d_bottom))
    return views


def sheet_path(path: str | Path) -> Path:
    """``path`` checked as a contact sheet's file before anything is built or rendered
    (that takes seconds): an image's name, where a file can be written (`cannot_write`).

    Raises:
        ConfigError: a folder, a name without an image suffix, or a folder that cannot be
            made or written (bad input, exit status 2).
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"--out {path} is a folder: name the image to write, e.g. sheet.png")
    formats = FigureCanvasBase.get_supported_filetypes()
    if path.suffix[1:].lower() not in formats:
        raise ConfigError(
            f"--out {path}: name an image file ({', '.join(f'.{f}' for f in sorted(formats))})"
        )
    why = cannot_write(path)
    if why:
        raise ConfigError(f"cannot write {path}: {why}")
    return path


def write_contact_sheet(
    scenario: Scenario,
    path: str | Path,
    sensors: SensorConfig | None = None,
    count: int = 6,
    poses: list[tuple[Pose, float]] | None = None,
) -> Path:
    """Render ``count`` views along the passage into one PNG at ``path``; returns it.

    Two views (colour + depth) per row pair, side by side, captioned with the distance
    from the start and the echo-sounder readings.
    """
    sensors = sensors or SensorConfig()
    poses = poses if poses is not None else passage_poses(scenario, count)
    views = render_views(scenario, sensors, poses)
    columns = 2  # pairs per row
    rows = -(-len(views) // columns)
    fig, axes = plt.subplots(
        rows, 2 * columns, figsize=(4 * 2 * columns * 0.8, 3.1 * rows * 0.8), squeeze=False
    )
    for ax in axes.flat:
        ax.axis("off")
    for k, view in enumerate(views):
        row, col = divmod(k, columns)
        colour_ax, depth_ax = axes[row, 2 * col], axes[row, 2 * col + 1]
        colour_ax.imshow(view.rgb, interpolation="antialiased")
        depth_ax.imshow(view.depth_png, cmap="gray", vmin=0, vmax=255, interpolation="antialiased")
        colour_ax.set_title(
            f"{view.distance_m:.1f} m in · top {view.d_top:.1f} m · bottom {view.d_bottom:.1f} m",
            fontsize=8,
            loc="left",
        )
        depth_ax.set_title(f"depth (0-{sensors.depth_max_m:g} m)", fontsize=8, loc="left")
    optics = sensors.optics
    lamps = f"{len(optics.fitted_lamps)} × {optics.lamp_lumens:g} lm"
    if optics.light_power is not None:
        lamps = f"lamps {optics.light_power:g}"
    fig.suptitle(
        f"{scenario.name} · {optics.water_name} water · {lamps} · "
        f"daylight {optics.daylight:g} · marine snow {optics.particles:g}/m³ · "
        f"seed {sensors.seed}",
        fontsize=10,
    )
    title_in = 0.35  # inches kept free above the views for the title
    fig.tight_layout(pad=0.4, rect=(0, 0, 1, 1 - title_in / fig.get_figheight()))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
