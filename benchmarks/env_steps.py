"""Steps per second of the Gymnasium environment at the paper's and at low resolutions.

For 640x480, 160x120 and 84x84, flies S4 (cave seed 0) with random actions
(``action_format="vector"``, ``action_space.sample()`` seeded, snapped to admissible
actions, so the vehicle really moves, collides and reaches exits) and prints:

- 1 env steps/s:   one ``gymnasium.make("cavenav/CaveNav-v0", ...)`` (with its TimeLimit),
                   reset whenever an episode ends; the resets' time is counted in
- ms/step:         the same as milliseconds per step, split into what the environment
                   measures itself (``info["timings"]``): sense (the observation's
                   ray cast and shading) and physics (swept collision, clearance,
                   progress), and the rest (resets, wrappers, the action's sampling and
                   snapping, the info dict)
- resets:          episodes ended during the timed steps (collisions, exits, budget);
                   a reset renders a frame too, so fewer resets make more steps a second
- vector steps/s:  ``gymnasium.vector.SyncVectorEnv`` of 2 such environments, counted as
                   environment steps (2 per vector step), resetting in the same step as
                   an episode ends (``AutoresetMode.SAME_STEP``), so every counted step is
                   a real transition

Each configuration is warmed up first (the cave is built, the kernels are loaded, the
lighting tables are made), then a fixed number of steps is timed. The target: 84x84 at
300 steps/s or more for one environment on 2 cores.

Run: make bench   (or: python benchmarks/env_steps.py [--steps N] [--warmup N])
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym

import cavenav  # noqa: F401 - registers cavenav/CaveNav-v0

RESOLUTIONS = ((640, 480), (160, 120), (84, 84))
TARGET = 300.0  # steps per second at 84x84, one environment


def make(resolution: tuple[int, int]) -> gym.Env:
    return gym.make(
        "cavenav/CaveNav-v0",
        scenario="S4",
        cave_seed=0,
        action_format="vector",
        resolution=resolution,
    )


def single(resolution: tuple[int, int], steps: int, warmup: int) -> dict[str, float]:
    """One environment: steps/s and the mean ms per step of sense, physics and the rest."""
    env = make(resolution)
    env.action_space.seed(0)
    env.reset(seed=0)
    for _ in range(warmup):
        *_, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    sense = physics = 0.0
    resets = 0
    start = time.perf_counter()
    for _ in range(steps):
        *_, terminated, truncated, info = env.step(env.action_space.sample())
        sense += info["timings"].sense_ms
        physics += info["timings"].physics_ms
        if terminated or truncated:
            env.reset()
            resets += 1
    elapsed = time.perf_counter() - start
    env.close()
    total_ms = 1e3 * elapsed / steps
    return {
        "steps_s": steps / elapsed,
        "ms": total_ms,
        "sense": sense / steps,
        "physics": physics / steps,
        "rest": total_ms - (sense + physics) / steps,
        "resets": resets,
    }


def vector(resolution: tuple[int, int], steps: int, warmup: int) -> tuple[float, int]:
    """A SyncVectorEnv of 2: environment steps per second (2 per vector step), and how
    many episodes ended during the timed steps."""
    envs = gym.vector.SyncVectorEnv(
        [lambda: make(resolution) for _ in range(2)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    envs.action_space.seed(0)
    envs.reset(seed=[0, 1])
    for _ in range(warmup):
        envs.step(envs.action_space.sample())
    rounds = max(1, steps // 2)
    ended = 0
    start = time.perf_counter()
    for _ in range(rounds):
        *_, terminated, truncated, _ = envs.step(envs.action_space.sample())
        ended += int((terminated | truncated).sum())
    elapsed = time.perf_counter() - start
    envs.close()
    return 2 * rounds / elapsed, ended


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=300, help="timed environment steps")
    parser.add_argument("--warmup", type=int, default=20, help="untimed steps first")
    args = parser.parse_args()
    print(
        f"{'resolution':<11} {'1 env steps/s':>13} {'ms/step':>8} {'sense':>6} "
        f"{'physics':>8} {'rest':>6} {'resets':>7} {'vector(2) steps/s':>18} {'resets':>7}"
    )
    rates = {}
    for resolution in RESOLUTIONS:
        one = single(resolution, args.steps, args.warmup)
        two, ended = vector(resolution, args.steps, args.warmup)
        rates[resolution] = one["steps_s"]
        name = f"{resolution[0]}x{resolution[1]}"
        print(
            f"{name:<11} {one['steps_s']:>13.1f} {one['ms']:>8.2f} {one['sense']:>6.2f} "
            f"{one['physics']:>8.2f} {one['rest']:>6.2f} {one['resets']:>7.0f} {two:>18.1f} "
            f"{ended:>7}"
        )
    low = rates[RESOLUTIONS[-1]]
    verdict = "met" if low >= TARGET else "not met"
    print(f"84x84, one environment: {low:.0f} steps/s (target >= {TARGET:.0f}: {verdict})")


if __name__ == "__main__":
    main()
