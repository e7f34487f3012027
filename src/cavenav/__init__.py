"""cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.

Importing the package registers the Gymnasium environments ``cavenav/CaveNav-v0``
(`cavenav.sim.env.CaveNavEnv`, 150 steps) and ``cavenav/CaveNav-vector-v0`` (the same for
learners: `cavenav.sim.env.learner_env`) so ``gymnasium.make`` finds them with no other
set-up.
"""

import os

# One BLAS thread: the pilots' small matrix products gain nothing from more, and idle BLAS
# threads spin after each call, taking both cores from the render that follows (measured:
# sensing in `cavenav run S4` 70-74 ms a step with them, 47-48 ms without). Read when numpy
# loads, so it is set before anything imports it; a user's own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# $CAVENAV_THREADS caps the threads of the render kernels and ray casts (all cores when
# unset): sweep workers run with one core each, so that N workers use N cores, not N**2
# threads fighting over them.
if os.environ.get("CAVENAV_THREADS"):
    os.environ.setdefault("NUMBA_NUM_THREADS", os.environ["CAVENAV_THREADS"])

import gymnasium  # noqa: E402

from cavenav.core import moved  # noqa: E402
from cavenav.core.types import STEP_BUDGET  # noqa: E402

moved.install()  # `import cavenav.env` and the other old names, for one release

__version__ = "0.1.0"
# What the caves and the frames of a seed look like. It changes only on purpose, when the
# geometry of the families or the image formation changes, and every summary.json,
# sweep.json, results.csv and report carries it: results of different sets do not
# compare. Set 1: the caves and images up to November 2026. Set 2 (issue 25): lamps
# rated in lumens with a hot spot, wet rock's specular highlights, a camera with a gain
# ceiling, black clamp, clipping, noise filter and JPEG compression. Set 3 (issue 25):
# the caves take the shapes of real ones (scallops, silt floors, keyholes, flat roofs,
# ledges, notches, angular breakdown, speleothems; generator version 2). Set 4: the
# same caves; the shading grid tells a smooth wall by its shading normals, so that a few
# per cent of the pixels are interpolated rather than shaded alone (a faster step).
# Set 5: the sharp bends of S4 and long turn along a short curve instead of at a point,
# which takes away the straight seam their outer walls had; the other families' caves
# are unchanged. Set 6 (issue 49): rock photographed at the centimetre scale; the
# BlueROV2 camera's own white balance; coastal and turbid water as murky as the Jerlov
# types they stand for; no rings along the passages (generator version 3); every block
# of breakdown fallen to rest on the floor or on other blocks.
SCENARIO_SET = "6"

__all__ = ["SCENARIO_SET", "__version__"]

if "cavenav/CaveNav-v0" not in gymnasium.registry:
    gymnasium.register(
        id="cavenav/CaveNav-v0",
        entry_point="cavenav.sim.env:CaveNavEnv",
        vector_entry_point="cavenav.sim.vector_env:CaveNavVectorEnv",
        max_episode_steps=STEP_BUDGET,
    )
if "cavenav/CaveNav-vector-v0" not in gymnasium.registry:
    # For learners: vector actions (a policy never meets the text space by accident),
    # 84 x 84 images and a reward that also asks for standoff and pays for the exit.
    gymnasium.register(
        id="cavenav/CaveNav-vector-v0",
        entry_point="cavenav.sim.env:learner_env",
        vector_entry_point="cavenav.sim.vector_env:learner_vector_env",
        max_episode_steps=STEP_BUDGET,
    )
