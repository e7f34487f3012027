"""Top-down and side-view plots of a trajectory inside its cave (SPEC section 7).

topdown.png projects every wall triangle onto the horizontal plane (the cave's
footprint) and draws the path coloured by clearance, and the cave line where one is
laid. side.png unrolls the path: distance travelled against height, with the ceiling and
floor straight above and below each point, so undulating and bending caves read the
same way.

Figures are made with `matplotlib.figure.Figure`, never pyplot: pyplot's global state is
not thread-safe, and sweeps finish several episodes at once in one process.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from cavenav.core.files import save_figure
from cavenav.core.types import Pose
from cavenav.episode.records import EpisodeSummary
from cavenav.world.guideline import Guideline
from cavenav.world.mesh import CaveMesh
from cavenav.world.procedural import along, arc_length
from cavenav.world.raycast import RayCaster
from cavenav.world.scenarios import ExitPortal, Scenario

__all__ = [
    "draw_exits",
    "draw_footprint",
    "draw_guideline",
    "footprint_raster",
    "plot_episode",
    "plot_flight",
]

_CMAP = "viridis"
# Light grey under the path's colours, as 8-bit RGBA (images are not rounded, lines are).
_FOOTPRINT_GREY = np.round(np.array(colormaps["Greys"](0.25)) * 255).astype(np.uint8)
_CREDIT = "Open Robotics / DARPA SubT"


def _coloured_path(ax: Axes, x: np.ndarray, y: np.ndarray, c: np.ndarray, norm: Normalize):
    segments = np.stack(
        [np.column_stack([x[:-1], y[:-1]]), np.column_stack([x[1:], y[1:]])], axis=1
    )
    lines = LineCollection(list(segments), cmap=_CMAP, norm=norm, linewidths=2.5, zorder=3)
    lines.set_array(0.5 * (c[:-1] + c[1:]))
    ax.add_collection(lines)
    ax.scatter(x, y, c=c, cmap=_CMAP, norm=norm, s=9, zorder=4)
    return lines


def draw_footprint(ax: Axes, mesh: CaveMesh) -> None:
    """The cave seen from above: every wall triangle projected onto the horizontal plane,
    filled in grey on a raster as fine as the figure (`footprint_raster`)."""
    covered, extent = footprint_raster(mesh)
    rgba = np.zeros((*covered.T.shape, 4), np.uint8)
    rgba[covered.T] = _FOOTPRINT_GREY
    image = ax.imshow(rgba, origin="lower", extent=extent, interpolation="nearest", rasterized=True)
    image.sticky_edges.x.clear()  # margins around the cave, as around any plotted data
    image.sticky_edges.y.clear()


def footprint_raster(
    mesh: CaveMesh, cells: int = 800, batch: int = 2_000_000
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Which cells of a grid over the cave's horizontal extent a wall triangle covers.

    Matplotlib draws a `tripcolor` of the mesh one path per triangle: 0.6 s at 87,000
    triangles and 31 s at 3 million. Here each triangle tests the centres of the cells
    of its bounding box, all triangles with the same box size at once: 0.35 s and 0.9 s.
    A triangle covers the cells of its corners and, when its box spans more than two
    cells either way, the cells of the box whose centre lies inside the triangle grown by
    moving each edge outward by half a cell (further than half a cell at sharp corners,
    never past the box), so thin triangles and the seams between them leave no gaps.
    Vertices that no triangle uses neither widen the grid nor mark a cell.

    Returns:
        ``covered``, (nx, ny) bool indexed [x, y], and its (left, right, bottom, top).
    """
    xy = mesh.vertices[:, :2].astype(np.float64)
    used = np.zeros(len(xy), bool)
    used[mesh.faces] = True  # a mask: 0.02 s at 3 million triangles, np.unique takes 5 s
    lo, hi = xy[used].min(axis=0), xy[used].max(axis=0)
    cell = max(float((hi - lo).max()) / cells, 1e-9)
    shape = np.maximum(np.ceil((hi - lo) / cell).astype(int), 1) + 1
    covered = np.zeros(shape, bool)
    position = (xy - lo) / cell  # of each vertex, in cells
    # Unused vertices may lie anywhere: clipped into the grid so the cast cannot overflow.
    corner = np.floor(np.clip(position, 0, shape - 1)).astype(np.int32)
    covered[corner[used, 0], corner[used, 1]] = True  # the cells of every triangle's corners
    # That is all a triangle within 2x2 cells (a fine mesh's) covers, bar a sliver of a
    # cell, under a pixel of the figure. Larger ones test the cells of their box.
    first = corner[mesh.faces].min(axis=1)
    size = corner[mesh.faces].max(axis=1) - first + 1
    large = np.flatnonzero((size > 2).any(axis=1))
    a, b, c = position[mesh.faces[large]].transpose(1, 0, 2)
    first, size = first[large], size[large]
    turn = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    clockwise = turn[:, None] < 0
    b, c = np.where(clockwise, c, b), np.where(clockwise, b, c)  # all counter-clockwise
    key = size[:, 0] * (size[:, 1].max(initial=0) + 1) + size[:, 1]
    for value in np.unique(key):
        group = np.flatnonzero(key == value)
        sx, sy = size[group[0]]
        dx, dy = (d.ravel() for d in np.meshgrid(np.arange(sx), np.arange(sy), indexing="ij"))
        for k in np.array_split(group, max(1, len(group) * sx * sy // batch)):
            x, y = first[k, :1] + dx, first[k, 1:] + dy  # (triangles, cells) cell indices
            inside = np.ones(x.shape, bool)
            for p, q in ((a[k], b[k]), (b[k], c[k]), (c[k], a[k])):
                edge = q - p
                length = np.maximum(np.hypot(edge[:, :1], edge[:, 1:]), 1e-12)
                left = edge[:, :1] * (y + 0.5 - p[:, 1:]) - edge[:, 1:] * (x + 0.5 - p[:, :1])
                inside &= left >= -0.5 * length
            covered[x[inside], y[inside]] = True
    top = lo + shape * cell
    return covered, (lo[0], top[0], lo[1], top[1])


def draw_exits(ax: Axes, exits: Sequence[ExitPortal]) -> None:
    """Each exit portal from above: a thick orange segment across the passage."""
    for k, portal in enumerate(exits):
        ex = np.asarray(portal.point)
        n = np.asarray(portal.normal)[:2]
        n = n / max(np.linalg.norm(n), 1e-9)
        across = np.array([-n[1], n[0]]) * portal.radius
        ax.plot(
            [ex[0] - across[0], ex[0] + across[0]],
            [ex[1] - across[1], ex[1] + across[1]],
            color="tab:orange",
            lw=3,
            zorder=5,
            label="exit" if k == 0 else None,
        )


def draw_guideline(ax: Axes, line: Guideline | None) -> None:
    """The cave line from above, as a diver's survey shows it: its spans between the
    tie-offs, dots at the ties and a chevron at each line arrow, pointing to the exit
    (white line drawn dark, to show on the light footprint)."""
    if line is None:
        return
    colour = "goldenrod" if line.colour == "yellow" else "0.2"
    ties = line.ties
    ax.plot(ties[:, 0], ties[:, 1], color=colour, lw=0.9, ls="--", zorder=4,
            label=f"cave line ({line.colour})")  # fmt: skip
    ax.plot(ties[:, 0], ties[:, 1], ".", color=colour, ms=3, zorder=4)
    for point, direction in zip(line.arrows, line.arrow_directions, strict=True):
        heading = float(np.degrees(np.arctan2(direction[1], direction[0])))
        ax.plot(*point[:2], marker=(3, 0, heading - 90.0), color=colour, ms=7, zorder=4)


def _title(s: EpisodeSummary) -> str:
    return (
        f"{s.scenario} · {s.pilot} · seed {'-' if s.seed is None else s.seed} · "
        f"{s.termination} after "
        f"{s.steps} steps · min clearance {s.min_clearance_m:.2f} m"
    )


def _finish(fig: Figure, ax: Axes, lines, scenario: Scenario, path: Path) -> None:
    fig.colorbar(lines, ax=ax, label="clearance to nearest surface (m)", shrink=0.8)
    if scenario.mesh.name.startswith("cave_") and scenario.mesh.name.endswith(".dae"):
        fig.text(0.01, 0.01, f"mesh: {_CREDIT}", fontsize=7, color="0.4")
    save_figure(fig, path, dpi=110, bbox_inches="tight")


def plot_episode(
    summary: EpisodeSummary | Mapping[str, Any],
    poses: Sequence[Pose],
    clearances: Sequence[float],
    scenario: Scenario,
    caster: RayCaster,
    out_dir: Path,
) -> dict[str, str]:
    """Write topdown.png and side.png into ``out_dir``; returns their file names.

    Args:
        summary: the episode's summary (title, collision pose), or its summary.json fields.
        poses: the trajectory as recorded.
        clearances: one clearance per pose.
    """
    summary = EpisodeSummary.model_validate(summary)
    p = np.array([pose.position for pose in poses])
    c = np.asarray(clearances)
    norm = Normalize(vmin=0.0, vmax=max(3.0, float(c.max())))
    _plot_topdown(summary, p, c, norm, scenario, out_dir / "topdown.png")
    _plot_side(summary, p, c, norm, scenario, caster, out_dir / "side.png")
    return {"topdown": "topdown.png", "side": "side.png"}


def _plot_topdown(
    summary: EpisodeSummary,
    p: np.ndarray,
    c: np.ndarray,
    norm: Normalize,
    scenario: Scenario,
    path: Path,
) -> None:
    """The path from above, over the cave's footprint, with the start, exits and collision.

    Args:
        p: (n, 3) float positions; c: (n,) float clearances, metres.
    """
    fig = Figure(figsize=(8, 8))
    ax = fig.subplots()
    draw_footprint(ax, scenario.mesh)
    lines = _coloured_path(ax, p[:, 0], p[:, 1], c, norm)
    ax.plot(*p[0, :2], marker="o", color="tab:green", ms=9, zorder=5, label="start")
    draw_exits(ax, scenario.exits)
    draw_guideline(ax, scenario.guideline)
    hit = summary.collision_pose
    if hit:
        ax.plot(hit.x, hit.y, marker="X", color="tab:red", ms=12, zorder=6, label="collision")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(_title(summary), fontsize=9)
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    _finish(fig, ax, lines, scenario, path)


def _plot_side(
    summary: EpisodeSummary,
    p: np.ndarray,
    c: np.ndarray,
    norm: Normalize,
    scenario: Scenario,
    caster: RayCaster,
    path: Path,
) -> None:
    """The path unrolled: distance along it against height, with the rock straight above
    and below every 0.25 m of it.

    Args:
        p: (n, 3) float positions; c: (n,) float clearances, metres.
    """
    dense, s_dense = _densify(p, 0.25)
    up = caster.first_hit(dense, np.array([0.0, 0.0, 1.0]))
    down = caster.first_hit(dense, np.array([0.0, 0.0, -1.0]))
    ceiling = np.where(np.isfinite(up), dense[:, 2] + up, np.nan)
    floor = np.where(np.isfinite(down), dense[:, 2] - down, np.nan)
    s_pose = arc_length(p)
    fig = Figure(figsize=(11, 4))
    ax = fig.subplots()
    lo = np.nanmin(floor) - 1.0 if np.isfinite(floor).any() else p[:, 2].min() - 3
    hi = np.nanmax(ceiling) + 1.0 if np.isfinite(ceiling).any() else p[:, 2].max() + 3
    ax.fill_between(s_dense, lo, floor, color="0.55", step="mid", label="rock")
    ax.fill_between(s_dense, ceiling, hi, color="0.55", step="mid")
    ax.fill_between(s_dense, floor, ceiling, color="#d9ecf2", step="mid", label="water")
    lines = _coloured_path(ax, s_pose, p[:, 2], c, norm)
    ax.plot(0, p[0, 2], marker="o", color="tab:green", ms=9, zorder=5, label="start")
    hit = summary.collision_pose
    if hit:
        s_hit = s_pose[-1] + float(np.linalg.norm(np.array([hit.x, hit.y, hit.z]) - p[-1]))
        ax.plot(s_hit, hit.z, marker="X", color="tab:red", ms=12, zorder=6, label="collision")
    ax.set_xlim(0, max(s_pose[-1], 1.0))
    ax.set_ylim(lo, hi)
    ax.set_xlabel("distance along the path (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(
        _title(summary) + " · ceiling and floor straight above and below the path", fontsize=9
    )
    ax.legend(loc="upper right", fontsize=8, ncols=4)
    _finish(fig, ax, lines, scenario, path)


def _densify(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` metres along a polyline, and their arc length."""
    if len(points) < 2:
        return points.copy(), np.zeros(len(points))
    s = arc_length(points)
    s_new = np.unique(np.concatenate([np.arange(0.0, s[-1], spacing), s]))
    return along(points, s_new), s_new


def plot_flight(
    steps: Sequence[Mapping[str, Any]], title: str, out_dir: Path, final_sigma_m: float = 0.0
) -> dict[str, str]:
    """A flight on a vehicle's own sensors (`cavenav.episode.on_vehicle`), where there is
    no cave model: topdown.png, the path as reported or reckoned with its one-sigma
    uncertainty around each pose; side.png, the path unrolled with the ceiling and floor
    the sounders read above and below it (left open where a sounder read nothing sure).
    Returns the file names.

    Args:
        steps: steps.jsonl's records (pose, position_sigma_m, d_top_m, d_bottom_m, and
            next_pose for the end of the last move).
        final_sigma_m: the uncertainty where the last move ended.
    """
    poses = [step["pose"] for step in steps] + [steps[-1].get("next_pose") or steps[-1]["pose"]]
    p = np.array([[pose["x"], pose["y"], pose["z"]] for pose in poses])
    sigma = [step.get("position_sigma_m") or 0.0 for step in steps] + [final_sigma_m]
    fig = Figure(figsize=(8, 8))
    ax = fig.subplots()
    ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=2, marker=".", zorder=3, label="path")
    for (x, y, _), radius in zip(p, sigma, strict=True):
        if radius > 0:
            ax.add_patch(Circle((x, y), radius, fill=False, color="tab:orange", alpha=0.5))
    ax.plot(*p[0, :2], marker="o", color="tab:green", ms=9, zorder=5, label="start")
    ax.plot([], [], color="tab:orange", label="one sigma of the reckoned position")
    centre = 0.5 * (p[:, :2].min(axis=0) + p[:, :2].max(axis=0))
    half = max(1.0, float(np.ptp(p[:, :2], axis=0).max()) / 2 + max(sigma, default=0.0) + 0.5)
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half))
    ax.set_aspect("equal")
    ax.set(xlabel="x (m)", ylabel="y (m)", title=title)
    ax.legend(loc="upper left", fontsize=8)
    save_figure(fig, out_dir / "topdown.png", dpi=110, bbox_inches="tight")
    _plot_sounded(steps, p, title, out_dir / "side.png")
    return {"topdown": "topdown.png", "side": "side.png"}


def _plot_sounded(
    steps: Sequence[Mapping[str, Any]], p: np.ndarray, title: str, path: Path
) -> None:
    """Distance along the path against height, with what the sounders read at each step."""
    s = arc_length(p)
    z = p[: len(steps), 2]
    top = np.array([np.nan if v.get("d_top_m") is None else v["d_top_m"] for v in steps])
    bottom = np.array([np.nan if v.get("d_bottom_m") is None else v["d_bottom_m"] for v in steps])
    fig = Figure(figsize=(11, 4))
    ax = fig.subplots()
    ceiling, floor = z + top, z - bottom
    known = np.concatenate([ceiling[np.isfinite(ceiling)], floor[np.isfinite(floor)], p[:, 2]])
    lo, hi = known.min() - 1.0, known.max() + 1.0
    at = s[: len(steps)]
    ax.fill_between(at, ceiling, hi, color="0.55", step="mid", label="rock the sounders read")
    ax.fill_between(at, lo, floor, color="0.55", step="mid")
    ax.plot(s, p[:, 2], color="tab:blue", lw=2, marker=".", zorder=3, label="path")
    ax.plot(0, p[0, 2], marker="o", color="tab:green", ms=9, zorder=5, label="start")
    ax.set(xlim=(0, max(s[-1], 1.0)), ylim=(lo, hi), xlabel="distance along the path (m)")
    ax.set(ylabel="z (m)", title=f"{title} · ceiling and floor as the sounders read them")
    ax.legend(loc="upper right", fontsize=8, ncols=3)
    save_figure(fig, path, dpi=110, bbox_inches="tight")
