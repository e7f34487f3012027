"""Who gets the cores between two ray casts: the sensors, not idle BLAS threads.

OpenBLAS (numpy's and scipy's matrix products) keeps its worker threads spinning for a
while after each call, waiting for the next one. A pilot or the shield that multiplies a
point cloud by a few directions just before the environment renders leaves those
threads spinning on the cores that Open3D's cast and numba's shading then need: on 2
cores the next observation took 70 ms instead of 48 (benchmarks/episode.py). The
products cavenav itself computes are small (thousands of points by a few hundred
directions) and no slower on one thread, so they run on one.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache, wraps
from typing import ParamSpec, TypeVar

from threadpoolctl import ThreadpoolController

__all__ = ["one_blas_thread"]

_P = ParamSpec("_P")
_R = TypeVar("_R")


@cache
def _controller() -> ThreadpoolController:
    # Made at the first call, when numpy's (and scipy's) BLAS are loaded; 0.02 ms a use.
    return ThreadpoolController()


def one_blas_thread(function: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorate ``function`` to run its matrix products on one BLAS thread (see above)."""

    @wraps(function)
    def limited(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with _controller().limit(limits=1, user_api="blas"):
            return function(*args, **kwargs)

    return limited
