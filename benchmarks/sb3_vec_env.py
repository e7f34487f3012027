"""Environment steps a second as Stable-Baselines3 steps them: the batched environment
through `cavenav.training.sb3_vec_env.SB3VecEnv`, against SB3's own `DummyVecEnv` over
the same number of single environments.

    python benchmarks/sb3_vec_env.py [--envs 16] [--steps 200] [--resolution 84x84] [--ppo 2048]

Both fly ``cavenav/CaveNav-vector-v0`` in one cave (random actions, episodes cut at 150
steps and reset within the step that ends them, as SB3 wants), from the same seeds, in
the same process, one after the other; the first steps of each are left out. With
``--ppo N``, also PPO's rate over N steps of learning (``MultiInputPolicy``, rollouts of
64 steps an environment), through each. Printed: the rates and their ratios.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from vector_env import arguments  # benchmarks/vector_env.py, beside this script

import cavenav  # noqa: F401 - registers the environments
from cavenav.sensors.camera import parse_resolution

ID = "cavenav/CaveNav-vector-v0"


def batched(envs: int, resolution: tuple[int, int]) -> Any:  # noqa: ANN401 - SB3's VecEnv
    from cavenav.training.sb3_vec_env import SB3VecEnv

    return SB3VecEnv(gym.make_vec(ID, num_envs=envs, vectorization_mode="vector_entry_point",
                                  resolution=resolution, cave_seed=0))  # fmt: skip


def one_by_one(envs: int, resolution: tuple[int, int]) -> Any:  # noqa: ANN401
    from stable_baselines3.common.vec_env import DummyVecEnv

    return DummyVecEnv([lambda: gym.make(ID, resolution=resolution, cave_seed=0)] * envs)


def step_rate(venv: Any, steps: int, warm: int) -> float:  # noqa: ANN401
    """Steps a second over ``steps`` steps of every environment, after ``warm``."""
    venv.seed(0)
    venv.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, (warm + steps, venv.num_envs, 4))
    for t in range(warm):
        venv.step(actions[t].astype(np.float32))
    started = time.perf_counter()
    for t in range(warm, warm + steps):
        venv.step(actions[t].astype(np.float32))
    return venv.num_envs * steps / (time.perf_counter() - started)


def ppo_rate(venv: Any, timesteps: int) -> float:  # noqa: ANN401
    """PPO's steps of learning a second: rollouts and updates."""
    from stable_baselines3 import PPO

    model = PPO("MultiInputPolicy", venv, n_steps=64, batch_size=64, seed=0, device="cpu")
    started = time.perf_counter()
    model.learn(total_timesteps=timesteps)
    return model.num_timesteps / (time.perf_counter() - started)


def measured(make: Callable[..., Any], args: argparse.Namespace) -> tuple[float, float | None]:
    size = parse_resolution(args.resolution)
    venv = make(args.envs, size)
    rate = step_rate(venv, args.steps, args.warm)
    ppo = ppo_rate(venv, args.ppo) if args.ppo else None
    venv.close()
    return rate, ppo


def main() -> None:
    parser = arguments(__doc__.split("\n\n")[0])
    parser.add_argument("--ppo", type=int, default=0, help="steps of PPO learning to time")
    args = parser.parse_args()
    fast, fast_ppo = measured(batched, args)
    slow, slow_ppo = measured(one_by_one, args)
    print(f"{args.envs} environments at {args.resolution}, {args.steps} steps each:")
    print(f"  SB3VecEnv (batched):          {fast:8.0f} steps/s")
    print(f"  DummyVecEnv (one by one):     {slow:8.0f} steps/s")
    print(f"  ratio:                        {fast / slow:8.2f}")
    if fast_ppo and slow_ppo:
        print(f"  PPO through SB3VecEnv:        {fast_ppo:8.0f} steps/s")
        print(f"  PPO through DummyVecEnv:      {slow_ppo:8.0f} steps/s")
        print(f"  ratio:                        {fast_ppo / slow_ppo:8.2f}")


if __name__ == "__main__":
    main()
