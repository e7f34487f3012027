"""Wall relief: how far cave walls stray from a smoothed copy of themselves, by scale.

For each generated family (S1-S5, crawl, maze, long; seed 0, default difficulty) and each
third-party mesh (the Open Robotics / DARPA SubT tiles in examples/meshes, the same files
as ../shared/data/meshes, loaded by `cavenav.world.mesh.load_mesh`, which honours their
declared unit and up axis), prints:

- relief at 1 m: the RMS distance of the wall from a copy smoothed at 1 m;
- its spectrum: the RMS relief in the bands 0.1-0.25, 0.25-0.5, 0.5-1 and 1-2 m, each
  the RMS distance between the copies smoothed at the band's two scales (the levels of
  a Laplacian pyramid), so that the four bands add up, in squares, to about the relief
  between 0.1 and 2 m;
- the median edge length: relief at wavelengths shorter than about two edges cannot be
  in the mesh at all (marching cubes at 0.15-0.25 m for the generated caves).

The method, chosen to work on irregular, open and artist-made meshes:

- Smoothing is heat diffusion over the surface (geodesic, never across a passage to
  the facing wall): the cotangent Laplacian L and the lumped area matrix M of the
  mesh (linear finite elements, right on irregular triangulations: a flat patch stays
  exactly in place however it is triangulated), k = 4 implicit steps of
  (M + t/k L) x' = M x on the vertex positions. Open portals get the natural boundary
  condition. Coincident vertices (COLLADA splits them per face) are welded first.
- A copy "smoothed at s metres" passes half the amplitude of a wall wave of wavelength
  s: the filter is twiced (2 S - S^2, Tukey), whose response to a wave of wavenumber
  kappa is 1 - (1 - g)^2 with g = (1 + t kappa^2 / k)^-k, and t is solved so that this
  is 1/2 at kappa = 2 pi / s. Twicing also cancels, to first order, the shrinkage every
  smoothing causes on a curved surface: a 5 m tube smoothed once would lose centimetres
  of radius, counted as relief it does not have.
- Distances are |x - x_s| per vertex, averaged in squares with each vertex's area (a
  third of its triangles'), so dense and sparse parts of a mesh count by area.

Run: python benchmarks/wall_relief.py   (about a minute; builds uncached caves first)
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu

from cavenav.world.mesh import CaveMesh, load_mesh
from cavenav.world.scenarios import SCENARIOS, load_scenario

MESHES = Path(__file__).resolve().parents[1] / "examples" / "meshes"
SCALES = (0.1, 0.25, 0.5, 1.0, 2.0)  # metres
BANDS = ((0.1, 0.25), (0.25, 0.5), (0.5, 1.0), (1.0, 2.0))
STEPS = 4  # implicit diffusion steps per smoothing
HALF = 1.0 - math.sqrt(0.5)  # g at which the twiced response 1 - (1 - g)^2 is 1/2


def weld(
    vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than ``tol`` metres (on a grid); drop faces left degenerate or
    slivers (a millionth of the median area: their cotangents swamp the sums in rounding) and
    vertices no face uses (they would have no area and make the diffusion singular)."""
    keys = np.round(vertices / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    p = vertices[first][faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    keep = area > 1e-6 * np.median(area)  # slivers: cotangents of 1e6 and more, no area
    faces = faces[keep]
    used, faces = np.unique(faces, return_inverse=True)  # drop vertices no face uses
    return vertices[first][used], faces.reshape(-1, 3)


def laplacian(vertices: np.ndarray, faces: np.ndarray) -> tuple[sparse.csc_matrix, np.ndarray]:
    """Cotangent Laplacian (n, n) (positive semi-definite) and lumped vertex areas (n,)."""
    n = len(vertices)
    p = vertices[faces]  # (m, 3, 3)
    rows, cols, weights = [], [], []
    for i in range(3):  # the angle at corner i faces the edge (j, k)
        j, k = (i + 1) % 3, (i + 2) % 3
        u, v = p[:, j] - p[:, i], p[:, k] - p[:, i]
        cross = np.linalg.norm(np.cross(u, v), axis=1)
        cot = np.einsum("ij,ij->i", u, v) / cross
        half = 0.5 * cot
        rows += [faces[:, j], faces[:, k]]
        cols += [faces[:, k], faces[:, j]]
        weights += [half, half]
    w = sparse.coo_matrix(
        (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsc()
    lap = sparse.diags(np.asarray(w.sum(axis=1)).ravel()) - w
    tri_area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    area = np.bincount(faces.ravel(), np.repeat(tri_area / 3.0, 3), minlength=n)
    return lap.tocsc(), area


def diffusion_time(scale: float, steps: int = STEPS) -> float:
    """t at which k implicit steps give g = HALF for a wave of wavelength ``scale``."""
    kappa = 2.0 * math.pi / scale
    return steps * (HALF ** (-1.0 / steps) - 1.0) / kappa**2


def smoothed(
    vertices: np.ndarray, lap: sparse.csc_matrix, area: np.ndarray, scale: float
) -> np.ndarray:
    """(n, 3) the vertices smoothed at ``scale`` metres: twiced implicit heat diffusion."""
    mass = sparse.diags(area)
    solve = splu((mass + diffusion_time(scale) / STEPS * lap).tocsc()).solve

    def once(x: np.ndarray) -> np.ndarray:
        for _ in range(STEPS):
            x = solve(area[:, None] * x)
        return x

    first = once(vertices)
    return 2.0 * first - once(first)


def relief(mesh: CaveMesh) -> tuple[float, list[float], float, int]:
    """(RMS relief at 1 m, RMS relief per band of BANDS, median edge length, vertices)."""
    vertices, faces = weld(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces))
    lap, area = laplacian(vertices, faces)
    copies = {s: smoothed(vertices, lap, area, s) for s in SCALES}
    weight = area / area.sum()

    def rms(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sqrt(weight @ np.sum((a - b) ** 2, axis=1)))

    edges = np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, axis=1)], axis=2)
    bands = [rms(copies[a], copies[b]) for a, b in BANDS]
    return rms(vertices, copies[1.0]), bands, float(np.median(edges)), len(vertices)


def main() -> None:
    start = time.perf_counter()
    meshes: list[tuple[str, str, CaveMesh]] = [
        ("generated", name, load_scenario(name, seed=0).mesh) for name in SCENARIOS
    ]
    meshes += [("third-party", path.stem, load_mesh(path)) for path in sorted(MESHES.glob("*.dae"))]
    band_names = " ".join(f"{f'{a:g}-{b:g} m':>10}" for a, b in BANDS)
    print(
        "RMS wall relief, metres (smoothing by heat diffusion over the surface; see the docstring)"
    )
    print(f"{'mesh':<24} {'source':<11} {'vertices':>8} {'edge':>6} {'at 1 m':>7} {band_names}")
    for source, name, mesh in meshes:
        at_1m, bands, edge, count = relief(mesh)
        cells = " ".join(f"{b:>10.3f}" for b in bands)
        print(f"{name:<24} {source:<11} {count:>8,} {edge:>6.2f} {at_1m:>7.3f} {cells}")
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
