"""Environment steps a second: the native batched environment against the same number of
environments stepped one after another (what `gymnasium.vector.SyncVectorEnv` does).

    python benchmarks/vector_env.py [--envs 16] [--steps 200] [--resolution 84x84]

Both fly ``cavenav/CaveNav-vector-v0`` (random actions, episodes cut at 150 steps and
reset as they end), from the same seeds, in the same process, one after the other; the
first steps of each (kernels loading, caves built) are left out of the timing; both
batch the observations as `SyncVectorEnv` does. The batched one shades its frames on as
many threads as Numba has (``--workers``: another number), one frame to a thread.
Printed: each one's rate, the ratio, and the bound the ray cast sets (the environments'
last rays, cast alone, a second). The issue's targets: 2,000 steps a second with 16
environments at 84x84 on 2 cores; at 640x480, 1.5 times a single environment's rate.
"""

from __future__ import annotations

import argparse
import time
from copy import deepcopy

import gymnasium as gym
import numpy as np
from gymnasium.vector.utils import concatenate, create_empty_array

import cavenav  # noqa: F401 - registers the environments
from cavenav.sensors.camera import parse_resolution

ID = "cavenav/CaveNav-vector-v0"


def batched_rate(
    envs: int, steps: int, resolution: tuple[int, int], warm: int, workers: int | None
) -> tuple[float, float]:
    """Steps a second batched, and the bound the cast sets: the cast alone of the rays
    the environments cast at the end, a second."""
    vector = gym.make_vec(ID, num_envs=envs, vectorization_mode="vector_entry_point",
                          resolution=resolution, cave_seed=0, workers=workers)  # fmt: skip
    vector.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (warm + steps, envs, 4)).astype(np.float32)
    for t in range(warm):
        vector.step(actions[t])
    started = time.perf_counter()
    for t in range(warm, warm + steps):
        vector.step(actions[t])
    rate = envs * steps / (time.perf_counter() - started)
    singles = vector.unwrapped.envs
    rays = np.concatenate([env.sensor_rays().copy() for env in singles])
    bound = cast_bound(singles[0].caster, rays, envs)
    vector.close()
    return rate, bound


def one_by_one_rate(envs: int, steps: int, resolution: tuple[int, int], warm: int) -> float:
    singles = [gym.make(ID, resolution=resolution, cave_seed=0) for _ in range(envs)]
    for i, env in enumerate(singles):
        env.reset(seed=i)
    actions = np.random.default_rng(0).uniform(-1, 1, (warm + steps, envs, 4)).astype(np.float32)
    ended = [False] * envs
    space = singles[0].observation_space
    batch = create_empty_array(space, envs)

    def step_all(t: int) -> None:  # as SyncVectorEnv does, less its batching of the infos
        observations = []
        for i, env in enumerate(singles):
            if ended[i]:
                observations.append(env.reset()[0])
                ended[i] = False
            else:
                observation, _, terminated, truncated, _ = env.step(actions[t, i])
                observations.append(observation)
                ended[i] = terminated or truncated
        deepcopy(concatenate(space, observations, batch))

    for t in range(warm):
        step_all(t)
    started = time.perf_counter()
    for t in range(warm, warm + steps):
        step_all(t)
    return envs * steps / (time.perf_counter() - started)


def cast_bound(caster: object, rays: np.ndarray, envs: int, repeats: int = 50) -> float:
    """Steps a second if a step cost only its share of one cast of every env's rays."""
    started = time.perf_counter()
    for _ in range(repeats):
        caster.cast_raw_rays(rays)  # type: ignore[attr-defined]
    return envs * repeats / (time.perf_counter() - started)


def arguments(description: str) -> argparse.ArgumentParser:
    """The options every environment-rate benchmark takes (also `sb3_vec_env.py`'s)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--resolution", default="84x84")
    parser.add_argument("--warm", type=int, default=5)
    return parser


def main() -> None:
    parser = arguments(__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=None, help="shading threads, batched")
    args = parser.parse_args()
    size = parse_resolution(args.resolution)
    batched, bound = batched_rate(args.envs, args.steps, size, args.warm, args.workers)
    alone = one_by_one_rate(args.envs, args.steps, size, args.warm)
    print(f"{args.envs} environments at {size[0]}x{size[1]}, {args.steps} steps each:")
    print(f"  batched (CaveNavVectorEnv):   {batched:8.0f} steps/s")
    print(f"  one after another (as Sync):  {alone:8.0f} steps/s")
    print(f"  ratio:                        {batched / alone:8.2f}")
    print(f"  the ray cast alone allows:    {bound:8.0f} steps/s")


if __name__ == "__main__":
    main()
