"""Train a small CNN pilot with PPO on the environment, within a budget of wall time.

The policy sees what the VLM pilot sees but text: the 84x84 colour image, the normalised
depth image and both echo sounders (``depth_m``, metres, is left out: it is the depth
image again at full precision). Stable-Baselines3's ``MultiInputPolicy`` gives each image
its own CNN (NatureCNN) and joins them with the sounders; the actions are four numbers
that the environment snaps to the admissible moves. The policy flies ``--caves`` training
caves of the family at once (cave seeds drawn below `cavenav.env.TRAINING_SEEDS`; the
held-out seeds, 1000 and up, are for evaluation), one environment each: building a cave
and its lighting takes seconds, so a fresh cave at every reset would leave no time to
learn. The reward is `cavenav.env.LEARNER_REWARD`: metres made good, minus 0.5 a step
per metre inside the 2 m standoff, minus 10 on a collision, plus 10 at the exit.

Writes to ``--out``: ``monitor-K.monitor.csv`` per cave (every episode: return, length,
seconds since the start, and whether it reached the exit or collided, as
Stable-Baselines3's ``Monitor`` writes it), ``ppo_cavenav.zip`` (the model), ``curve.png``
(return and exits over the steps) and ``evaluation.json``: the trained policy flown
deterministically once in each of ``--evaluate`` held-out caves (seeds 1000 and up).

Run: pip install -e '.[learn]'; python examples/train_ppo.py --minutes 60 --out ppo-run
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import cavenav.env  # registers cavenav/CaveNav-vector-v0

SEEN = ("rgb", "depth", "d_top", "d_bottom")


def make_env(scenario: str, cave_seed: int, out: Path) -> gym.Env:
    """The vector environment in one training cave, with what the policy sees, logged."""
    from stable_baselines3.common.monitor import Monitor

    env = gym.make("cavenav/CaveNav-vector-v0", scenario=scenario, cave_seed=cave_seed)
    env = gym.wrappers.FilterObservation(env, list(SEEN))
    log = out / f"monitor-{cave_seed}"
    return Monitor(env, str(log), info_keywords=("exit", "collision"))


def train(scenario: str, caves: int, minutes: float, steps: int, seed: int, out: Path) -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv

    class WallClock(BaseCallback):
        """Stops learning once the budget of wall time is spent."""

        def __init__(self, seconds: float):
            super().__init__()
            self.deadline = time.monotonic() + seconds

        def _on_step(self) -> bool:
            return time.monotonic() < self.deadline

    out.mkdir(parents=True, exist_ok=True)
    seeds = np.random.default_rng(seed).choice(cavenav.env.TRAINING_SEEDS, caves, replace=False)
    envs = DummyVecEnv([lambda k=int(k): make_env(scenario, k, out) for k in seeds])
    model = PPO(
        "MultiInputPolicy",
        envs,
        n_steps=max(512 // caves, 16),
        batch_size=64,
        learning_rate=3e-4,
        seed=seed,
        device="cpu",
        verbose=0,
    )
    model.learn(total_timesteps=steps, callback=WallClock(60.0 * minutes))
    model.save(out / "ppo_cavenav")
    plot(out)


def episodes(out: Path) -> dict[str, np.ndarray]:
    """Every cave's episodes from the monitors' logs, in the order they ended: return
    ``r``, length ``l``, seconds ``t``, and ``exit`` and ``collision`` as 0 or 1."""
    rows = []
    for log in sorted(out.glob("monitor-*.monitor.csv")):
        with log.open() as f:
            f.readline()  # the monitor's JSON header
            rows += list(csv.DictReader(f))
    rows.sort(key=lambda row: float(row["t"]))
    columns = {key: np.array([float(row[key]) for row in rows]) for key in ("r", "l", "t")}
    for key in ("exit", "collision"):
        columns[key] = np.array([row[key] == "True" for row in rows], float)
    return columns


def trailing_mean(values: np.ndarray, window: int) -> np.ndarray:
    """The mean of each value and the ``window - 1`` before it (fewer at the start)."""
    sums = np.cumsum(np.concatenate([[0.0], values]))
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - window, 0)
    return (sums[ends] - sums[starts]) / (ends - starts)


def plot(out: Path, window: int = 50) -> None:
    """``curve.png``: each episode's return and a trailing mean, and the trailing share of
    episodes that reached the exit or collided, against the environment steps flown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = episodes(out)
    steps = np.cumsum(runs["l"])
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    top.plot(steps, runs["r"], ".", alpha=0.2, label="episode return")
    top.plot(steps, trailing_mean(runs["r"], window), label=f"mean of the last {window}")
    top.set_ylabel("return")
    top.legend()
    for key, label in (("exit", "reached the exit"), ("collision", "collided")):
        bottom.plot(steps, trailing_mean(runs[key], window), label=label)
    bottom.set_ylabel(f"share of the last {window}")
    bottom.set_xlabel("environment steps")
    bottom.set_ylim(-0.02, 1.02)
    bottom.legend()
    fig.tight_layout()
    fig.savefig(out / "curve.png", dpi=100)


def evaluate(out: Path, scenario: str, seeds: range) -> dict[str, float]:
    """Fly the saved policy, deterministically, once in each held-out cave of ``seeds``;
    writes and returns the share that reached the exit, that collided, and the mean
    metres made good."""
    from stable_baselines3 import PPO

    model = PPO.load(out / "ppo_cavenav", device="cpu")
    exits = collisions = 0
    made_good = []
    for seed in seeds:
        env = gym.make("cavenav/CaveNav-vector-v0", scenario=scenario, cave_seed=seed)
        env = gym.wrappers.FilterObservation(env, list(SEEN))
        obs, info = env.reset(seed=seed)
        done = False
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        exits += info["exit"]
        collisions += info["collision"]
        made_good.append(info["progress_m"])
    result = {
        "caves": len(seeds),
        "exit_share": exits / len(seeds),
        "collision_share": collisions / len(seeds),
        "mean_progress_m": float(np.mean(made_good)),
    }
    (out / "evaluation.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scenario", default="S1", help="the family to train on")
    parser.add_argument("--caves", type=int, default=8, help="training caves flown at once")
    parser.add_argument("--minutes", type=float, default=60.0, help="wall-time budget")
    parser.add_argument("--steps", type=int, default=10_000_000, help="most steps to take")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("ppo-run"))
    parser.add_argument(
        "--evaluate", type=int, default=10, help="held-out caves to fly afterwards (1000 up)"
    )
    args = parser.parse_args()
    started = time.monotonic()
    train(args.scenario, args.caves, args.minutes, args.steps, args.seed, args.out)
    spent = (time.monotonic() - started) / 60
    print(f"trained for {spent:.1f} min; the model, its log and curve are in {args.out}")
    if args.evaluate:
        held_out = range(cavenav.env.TRAINING_SEEDS, cavenav.env.TRAINING_SEEDS + args.evaluate)
        print(json.dumps(evaluate(args.out, args.scenario, held_out)))


if __name__ == "__main__":
    main()
