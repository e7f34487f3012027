"""Ray casting and distance queries over a cave mesh, backed by Open3D.

Measured here (2 cores): Open3D's `RaycastingScene` casts a 640x480 frame in ~40 ms and
answers a closest-point query in ~0.03 ms, against 75-95 ms and ~11 ms for trimesh with
Embree; clearance is queried every step, so Open3D wins.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
import types
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np

from cavenav.core.errors import DependencyError
from cavenav.world.mesh import CaveMesh

__all__ = ["RayCaster"]

# Threads per cast: $CAVENAV_THREADS (set by sweep workers, one core each), else 0 = all.
_THREADS = int(os.environ.get("CAVENAV_THREADS") or 0)

# Scenes by mesh and thread, while the mesh lives: loading a scenario file measures its
# passage (`cavenav.world.units.check_units`), then the environment asks again for the same
# mesh, and building the BVH takes 1.5-5 s at 3 million triangles. Threads do not share
# a scene: sweeps fly one cave on several threads, each with a scene of its own as before.
_SCENES: weakref.WeakKeyDictionary[CaveMesh, dict[int, Any]] = weakref.WeakKeyDictionary()
_SCENES_LOCK = threading.Lock()


# Open3D's visualization package imports this module, its Plotly/Dash web viewer, at
# `import open3d`: 0.75 s of the 1.3 s the import takes, in every process, for a viewer
# cavenav never opens. A stand-in takes its place until one of its functions is called.
_PLOTLY_VIEWER = "open3d.visualization.draw_plotly"


def _defer_plotly_viewer() -> None:
    """Put a stand-in for `_PLOTLY_VIEWER` in `sys.modules` that imports the real module,
    and calls it, the first time one of its functions is called."""
    stand_in = types.ModuleType(_PLOTLY_VIEWER, "loaded on first use (cavenav.world.raycast)")
    # One forwarder per name, so that the package's bindings can be recognised later.
    handed_out: dict[str, Callable[..., Any]] = {}

    def load() -> types.ModuleType:
        if sys.modules.get(_PLOTLY_VIEWER) is stand_in:
            del sys.modules[_PLOTLY_VIEWER]
        real = importlib.import_module(_PLOTLY_VIEWER)
        # Importing a submodule binds it on its package under its own name: here over the
        # function `draw_plotly` that `open3d.visualization` took from the stand-in, which
        # would leave `o3d.visualization.draw_plotly(...)` calling a module. Give the
        # package the real functions for every name it still holds from the stand-in.
        package = sys.modules.get(_PLOTLY_VIEWER.rpartition(".")[0])
        if package is not None:
            for name, forwarder in handed_out.items():
                if getattr(package, name, None) in (forwarder, real):
                    setattr(package, name, getattr(real, name))
        return real

    def forward(name: str) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            return getattr(load(), name)(*args, **kwargs)

        return call

    def module_getattr(name: str) -> Callable[..., Any]:  # `from ... import name`
        if name.startswith("_"):
            raise AttributeError(name)
        if name not in handed_out:
            handed_out[name] = forward(name)
        return handed_out[name]

    stand_in.__getattr__ = module_getattr  # type: ignore[method-assign]
    sys.modules[_PLOTLY_VIEWER] = stand_in


def _import_open3d():  # noqa: ANN202 - module type
    if "open3d" not in sys.modules and _PLOTLY_VIEWER not in sys.modules:
        _defer_plotly_viewer()
    try:
        import open3d as o3d
    except ImportError as exc:
        hint = (
            "sudo apt-get install -y libusb-1.0-0"
            if "libusb" in str(exc)
            else "pip install open3d-cpu==0.20.0"
        )
        raise DependencyError(f"Open3D cannot be imported ({exc}); fix with: {hint}") from None
    return o3d


class RayCaster:
    """Owns the acceleration structure of one mesh; every geometric query goes here."""

    def __init__(self, mesh: CaveMesh):
        o3d = _import_open3d()
        self._o3d = o3d
        self.mesh = mesh
        thread = threading.get_ident()
        with _SCENES_LOCK:
            scene = _SCENES.get(mesh, {}).get(thread)
        if scene is None:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                o3d.core.Tensor(mesh.faces.astype(np.uint32)),
            )
            with _SCENES_LOCK:
                _SCENES.setdefault(mesh, {})[thread] = scene
        self._scene = scene

    def _rays(self, origins: np.ndarray, directions: np.ndarray):  # noqa: ANN202
        origins, directions = np.asarray(origins), np.asarray(directions)
        shape = np.broadcast_shapes(origins.shape, directions.shape)
        rays = np.empty((*shape[:-1], 6), np.float32)
        rays[..., :3] = origins
        rays[..., 3:] = directions
        return self._o3d.core.Tensor.from_numpy(rays.reshape(-1, 6)), shape[:-1]

    def cast_raw_rays(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        """Cast a C-contiguous (n, 6) float32 array of (origin, direction) rows as is.

        The renderer's fast path: no copies, and Open3D's outputs come back unconverted
        as flat numpy arrays: ``t_hit``, ``primitive_normals``, ``primitive_ids``
        (uint32, 0xFFFFFFFF where a ray escapes) and ``primitive_uvs`` (barycentric
        (u, v) of the hit: point = (1 - u - v) a + u b + v c).
        """
        out = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays), nthreads=_THREADS)
        keys = ("t_hit", "primitive_ids", "primitive_normals", "primitive_uvs")
        return {k: out[k].numpy() for k in keys}

    def first_hit(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(...) float32 ray parameter of the first hit only; cheaper than `cast`."""
        rays, shape = self._rays(origins, directions)
        return self._scene.cast_rays(rays, nthreads=_THREADS)["t_hit"].numpy().reshape(shape)

    def count_intersections(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(...) int number of surfaces each infinite ray crosses."""
        rays, shape = self._rays(origins, directions)
        return self._scene.count_intersections(rays).numpy().reshape(shape)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(...) float32 unsigned distance from each point in (..., 3) to the surface."""
        pts = np.asarray(points, np.float32)
        query = self._o3d.core.Tensor(np.ascontiguousarray(pts.reshape(-1, 3)))
        return self._scene.compute_distance(query).numpy().reshape(pts.shape[:-1])

    def closest_points(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) float32 nearest surface point to each point in (..., 3)."""
        pts = np.asarray(points, np.float32)
        query = self._o3d.core.Tensor(np.ascontiguousarray(pts.reshape(-1, 3)))
        out = self._scene.compute_closest_points(query)["points"].numpy()
        return out.reshape(pts.shape)
