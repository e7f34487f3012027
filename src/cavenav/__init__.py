"""cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.

Importing the package registers the Gymnasium environment ``cavenav/CaveNav-v0``
(`cavenav.env.CaveNavEnv`, 150 steps) so ``gymnasium.make`` finds it with no other set-up.
"""

import gymnasium

__version__ = "0.1.0"

__all__ = ["__version__"]

if "cavenav/CaveNav-v0" not in gymnasium.registry:
    gymnasium.register(
        id="cavenav/CaveNav-v0",
        entry_point="cavenav.env:CaveNavEnv",
        max_episode_steps=150,
    )
