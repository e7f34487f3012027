"""Train a small CNN pilot with PPO on the environment, within a budget of wall time.

The policy sees what the VLM pilot sees but text: the 84x84 colour image, the normalised
depth image and both echo sounders (``depth_m``, metres, is left out: it is the depth
image again at full precision). Stable-Baselines3's ``MultiInputPolicy`` gives each image
its own CNN (NatureCNN) and joins them with the sounders; the actions are four numbers
that the environment snaps to the admissible moves. The policy flies ``--caves`` training
caves of the family at once, or of several families in turn (``--scenario S1,S2,S3``)
(cave seeds drawn below `cavenav.sim.env.TRAINING_SEEDS`; the
held-out seeds, 1000 and up, are for evaluation), one environment each: building a cave
and its lighting takes seconds, so a fresh cave at every reset would leave no time to
learn. The reward is `cavenav.sim.env.LEARNER_REWARD`: metres made good, minus 0.5 a step
per metre inside the 2 m standoff, minus 10 on a collision, plus 10 at the exit.

Writes to ``--out``: ``monitor-K.monitor.csv`` per cave (every episode: return, length,
seconds since the start, and whether it reached the exit or collided, as
Stable-Baselines3's ``Monitor`` writes it), ``ppo_cavenav.zip`` (the last policy),
``best.zip`` (the policy whose last 100 episodes reached the exit most often), ``curve.png``
(return and exits over the steps) and ``evaluation.json``: both policies flown
deterministically once in each of ``--evaluate`` held-out caves (seeds 1000 and up).
``cavenav run S1 --pilot policy --policy ppo-run/best.zip`` flies one like any other pilot.

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

import cavenav.sim.env  # registers cavenav/CaveNav-vector-v0

SEEN = ("rgb", "depth", "d_top", "d_bottom")
# The policy's first spread of each action, as a share of its largest move: 0.6 m of
# surge, 0.37 m of sway, 0.74 m of heave and 24 degrees of yaw. A spread of 1 everywhere
# (Stable-Baselines3's default) turns a fresh policy through +-180 degrees a step, and it
# meets a wall in three steps, over and over, learning nothing.
FIRST_SPREAD = (0.6, 0.37, 0.37, 0.135)


def make_env(scenario: str, cave_seed: int, out: Path) -> gym.Env:
    """The vector environment in one training cave, with what the policy sees, logged."""
    from stable_baselines3.common.monitor import Monitor

    log = out / f"monitor-{cave_seed}"
    return Monitor(seen(scenario, cave_seed), str(log), info_keywords=("exit", "collision"))


def seen(scenario: str, cave_seed: int) -> gym.Env:
    """The vector environment in one cave as the policy meets it: the keys of `SEEN`, and
    actions from -1 to 1 (each scaled to its largest move; `cavenav.pilots.policy` undoes
    this when the policy flies), because a Gaussian policy explores with one spread for
    every action, and a degree of yaw is not a metre of surge."""
    env = gym.make("cavenav/CaveNav-vector-v0", scenario=scenario, cave_seed=cave_seed)
    env = gym.wrappers.FilterObservation(env, list(SEEN))
    return gym.wrappers.RescaleAction(env, np.float32(-1.0), np.float32(1.0))


def train(
    families: list[str], caves: int, minutes: float, steps: int, seed: int, out: Path
) -> None:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv

    class Budget(BaseCallback):
        """Stops learning once the budget of wall time is spent, and saves the policy as
        ``best.zip`` whenever the last `WINDOW` episodes reached the exit more often
        than any earlier window did (PPO can unlearn: the last policy is not the best)."""

        def __init__(self, seconds: float):
            super().__init__()
            self.deadline = time.monotonic() + seconds
            self.exits: list[bool] = []
            self.best = -1.0

        def _on_step(self) -> bool:
            self.exits += [i["episode"]["exit"] for i in self.locals["infos"] if "episode" in i]
            return time.monotonic() < self.deadline

        def _on_rollout_end(self) -> None:
            if len(self.exits) < WINDOW:
                return
            share = float(np.mean(self.exits[-WINDOW:]))
            if share > self.best:
                self.best = share
                self.model.save(out / "best")

    out.mkdir(parents=True, exist_ok=True)
    seeds = np.random.default_rng(seed).choice(cavenav.sim.env.TRAINING_SEEDS, caves, replace=False)
    flown = [(families[i % len(families)], int(k)) for i, k in enumerate(seeds)]  # in turn
    envs = DummyVecEnv([lambda f=f, k=k: make_env(f, k, out) for f, k in flown])
    budget = Budget(60.0 * minutes)
    deadline = budget.deadline  # the schedule is saved with the model: it holds no env

    def learning_rate(_: float) -> float:
        """3e-4, falling linearly to 0 as the wall-time budget runs out."""
        return 3e-4 * max(deadline - time.monotonic(), 0.0) / (60.0 * minutes)

    model = PPO(
        "MultiInputPolicy",
        envs,
        n_steps=max(1024 // caves, 16),
        batch_size=256,
        n_epochs=5,
        learning_rate=learning_rate,
        seed=seed,
        device="cpu",
        verbose=0,
    )
    with torch.no_grad():  # explore as a pilot would: a little yaw, more surge
        model.policy.log_std.copy_(torch.log(torch.tensor(FIRST_SPREAD)))
    model.learn(total_timesteps=steps, callback=budget)
    model.save(out / "ppo_cavenav")
    plot(out)


WINDOW = 100  # episodes in a trailing share


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


def plot(out: Path, window: int = WINDOW) -> None:
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


def evaluate(out: Path, families: list[str], seeds: range) -> dict[str, dict[str, float]]:
    """Fly the last policy and the best (``best.zip``, when a window was complete), each
    deterministically once in each held-out cave of ``seeds`` of each family; writes and
    returns, per policy, the share that reached the exit, that collided, and the mean
    metres made good."""
    from stable_baselines3 import PPO

    result = {}
    for name in ("ppo_cavenav", "best"):
        if not (out / f"{name}.zip").exists():
            continue
        model = PPO.load(out / name, device="cpu")
        exits = collisions = 0
        made_good = []
        flown = [(family, seed) for family in families for seed in seeds]
        for family, seed in flown:
            env = seen(family, seed)
            obs, info = env.reset(seed=seed)
            done = False
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
            exits += info["exit"]
            collisions += info["collision"]
            made_good.append(info["progress_m"])
        result[name] = {
            "caves": len(flown),
            "exit_share": exits / len(flown),
            "collision_share": collisions / len(flown),
            "mean_progress_m": float(np.mean(made_good)),
        }
    (out / "evaluation.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--scenario", default="S1", help="the family to train on, or several: S1,S2,S3,S4,S5"
    )
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
    families = args.scenario.split(",")
    train(families, args.caves, args.minutes, args.steps, args.seed, args.out)
    spent = (time.monotonic() - started) / 60
    print(f"trained for {spent:.1f} min; the model, its log and curve are in {args.out}")
    if args.evaluate:
        held_out = range(
            cavenav.sim.env.TRAINING_SEEDS, cavenav.sim.env.TRAINING_SEEDS + args.evaluate
        )
        print(json.dumps(evaluate(args.out, families, held_out)))


if __name__ == "__main__":
    main()
