"""Rings: whether the relief of cave walls repeats along the passage (issue 49).

For each generated family (S1-S5, crawl, maze, long; seed 0, default difficulty) along
its own centre line, and each third-party mesh (the Open Robotics / DARPA SubT tiles in
examples/meshes, the same files as ../shared/data/meshes, loaded by
`cavenav.world.mesh.load_mesh`) along `cavenav.world.rings.portal_axis` (the shortest
path between its two farthest portals, centred by rays), prints:

- the radius spectrum's peak factor: how far the tallest line of the spectrum of wall
  radius along the axis stands above its neighbours (wavelengths 0.2-2 m), where it
  lies, and the RMS of the relief in that line, millimetres;
- the crease spectrum's peak factor and where it lies: the same for how sharply the
  wall bends along the axis, averaged around each eighth of the wall, which sees rings
  whose strength repeats where their height does not (lattice noise, a jittered
  lattice of scallops, marching cubes' slabs, seams between the centre line's samples);
- both again with the floor left out (rays within 45 degrees of straight down: a
  sediment floor's ripples repeat as ripples do);
- the median edge length: a line at a wavelength of about two edges is the mesh's own.

The method is `cavenav.world.rings.ring_spectra`'s docstring: rays from the axis every
5 cm, 64 around; objects in the passage and openings left out; Welch spectra in 12.8 m
Hann windows; a bin's factor is its power over the median of its neighbours within a
factor 2 in wavelength once their power-law trend is taken out. A cave passes when
neither factor exceeds `RING_LIMIT` (4): relief with no preferred scale reads 1.5-3.

Run: python benchmarks/ring_spectrum.py   (about 5 s with the caves cached; a minute
when it builds them first)
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cavenav.world.mesh import CaveMesh, load_mesh
from cavenav.world.raycast import RayCaster
from cavenav.world.rings import RING_LIMIT, RingSpectra, portal_axis, ring_spectra
from cavenav.world.scenarios import SCENARIOS, load_scenario

MESHES = Path(__file__).resolve().parents[1] / "examples" / "meshes"


def median_edge(mesh: CaveMesh) -> float:
    """The median length of the mesh's triangle edges, metres."""
    corners = mesh.vertices[mesh.faces]
    return float(np.median(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)))


def cells(found: RingSpectra) -> str:
    """One measurement's columns: radius factor, where, line RMS (mm); crease factor, where."""
    radius, crease = found.radius, found.crease
    return (
        f"{radius.peak_factor:>6.1f} {radius.peak_wavelength:>4.2f} {radius.line_rms * 1e3:>4.1f} "
        f"{crease.peak_factor:>6.1f} {crease.peak_wavelength:>4.2f}"
    )


def main() -> None:
    start = time.perf_counter()
    passages: list[tuple[str, str, CaveMesh, np.ndarray | None]] = []
    for name in SCENARIOS:
        scenario = load_scenario(name, seed=0)
        passages.append(("generated", name, scenario.mesh, scenario.centreline))
    for path in sorted(MESHES.glob("*.dae")):
        passages.append(("third-party", path.stem, load_mesh(path), None))
    print(
        "Peak factors of the spectra along the axis, wavelengths 0.2-2 m (limit "
        f"{RING_LIMIT:g}): where the tallest line lies (m) and, for the radius, its RMS (mm)"
    )
    group = f"{'radius':>6} {'at':>4} {'mm':>4} {'crease':>6} {'at':>4}"
    print(f"{'':<41} | {'the whole wall':^28} | {'floor left out':^28} |")
    print(f"{'mesh':<18} {'source':<11} {'edge':>4} {'axis':>5} | {group} | {group} | ok")
    for source, name, mesh, axis in passages:
        caster = RayCaster(mesh)
        axis = portal_axis(mesh, caster) if axis is None else axis
        whole, rock = ring_spectra(caster, axis), ring_spectra(caster, axis, floor=False)
        ok = "yes" if max(whole.peak_factor, rock.peak_factor) <= RING_LIMIT else "no"
        print(
            f"{name:<18} {source:<11} {median_edge(mesh):>4.2f} {whole.length_m:>5.0f} | "
            f"{cells(whole)} | {cells(rock)} | {ok}"
        )
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
