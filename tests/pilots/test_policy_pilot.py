"""The learned pilot: a Stable-Baselines3 model flies `cavenav run` and sweeps as it acted
in the environment it was trained in."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import cavenav  # noqa: F401 - registers the environments
from cavenav.core.errors import ConfigError
from cavenav.motion.actions import snap_action
from cavenav.pilots.factory import PilotSpec
from cavenav.pilots.policy import PolicyPilot
from tests.conftest import cavenav as cli

pytest.importorskip("stable_baselines3")
pytestmark = pytest.mark.slow  # torch loads in each test's first model

SEEN = ["rgb", "depth", "d_top", "d_bottom"]


def trained_env(unit_actions: bool) -> gym.Env:
    """S1, cave 0, as a learner meets it: what the policy sees, actions in [-1, 1] or not."""
    env = gym.make("cavenav/CaveNav-vector-v0", scenario="S1", cave_seed=0)
    env = gym.wrappers.FilterObservation(env, SEEN)
    if unit_actions:
        env = gym.wrappers.RescaleAction(env, np.float32(-1.0), np.float32(1.0))
    return env


@pytest.fixture(scope="module")
def ppo_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained PPO policy on unit actions whose mean action moves and turns, and
    changes with what it sees (a fresh policy's mean is ~0: it would only ever hold)."""
    import torch
    from stable_baselines3 import PPO

    model = PPO("MultiInputPolicy", trained_env(True), n_steps=16, batch_size=16, seed=3)
    with torch.no_grad():
        model.policy.action_net.weight.mul_(300.0)
        model.policy.action_net.bias.copy_(torch.tensor([0.6, 0.0, 0.0, 0.0]))
    path = tmp_path_factory.mktemp("ppo") / "policy.zip"
    model.save(path)
    return path


def test_a_policy_flies_cavenav_run_as_it_acts_in_the_environment(ppo_file: Path, tmp_path):
    from stable_baselines3 import PPO

    model, env = PPO.load(ppo_file, device="cpu"), trained_env(True)
    obs, _ = env.reset(seed=0)
    in_env, done = [], False
    while not done and len(in_env) < 12:
        vector, _ = model.predict(obs, deterministic=True)
        obs, _, terminated, truncated, info = env.step(vector)
        in_env.append(info["action"])
        done = terminated or truncated
    assert len(set(in_env)) > 2  # the test means something: the policy varies its moves

    done_run = cli("run", "S1", "--pilot", "policy", "--policy", str(ppo_file), "--steps", "12",
                   "--no-frames", "--out", str(tmp_path))  # fmt: skip
    assert done_run.returncode == 0, done_run.stderr
    assert "84x84, as the policy saw it" in done_run.stdout
    (run_dir,) = tmp_path.iterdir()
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert [step["action"] for step in steps][: len(in_env)] == in_env
    assert steps[0]["justification"].startswith("policy policy.zip: (df, dr, dz, dpsi) = (")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["pilot"] == f"policy:{ppo_file.parent.name}/policy"


def test_a_policy_on_the_environments_own_action_box_is_read_as_is(tmp_path: Path):
    """SAC squashes its actions into the box it was trained on: here the environment's
    metres and degrees, which the pilot then takes without rescaling."""
    import torch
    from stable_baselines3 import SAC

    env = trained_env(False)
    model = SAC("MultiInputPolicy", env, buffer_size=64, seed=0)
    with torch.no_grad():
        model.policy.actor.mu.bias.copy_(torch.tensor([0.8, -0.5, 0.3, 0.4]))
    model.save(tmp_path / "sac.zip")
    obs, info = env.reset(seed=0)
    expected, _ = model.predict(obs, deterministic=True)
    decision = PolicyPilot(tmp_path / "sac.zip").decide(info["observation"])
    assert decision.action == snap_action(expected)
    assert decision.action.forward > 0 and decision.action.yaw_deg > 0


def test_a_sweep_records_which_model_flew_and_refuses_to_resume_with_another(
    ppo_file: Path, tmp_path: Path
):
    model = tmp_path / "model.zip"
    model.write_bytes(ppo_file.read_bytes())
    sweep = [
        "eval", "--scenarios", "S1", "--seeds", "0", "--pilot", "policy", "--policy", str(model),
        "--steps", "5", "--frames", "none", "--workers", "1", "--no-report",
        "--out", str(tmp_path / "sweep"),
    ]  # fmt: skip
    done = cli(*sweep)
    assert done.returncode == 0, done.stderr
    recorded = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    assert recorded["pilot"]["label"] == f"policy:{tmp_path.name}/model"
    assert (
        recorded["pilot"]["policy_sha256"]
        == PilotSpec("policy", policy=str(model)).to_dict()["policy_sha256"]
    )
    assert recorded["sensors"]["resolution"] == [84, 84]
    rows = (tmp_path / "sweep" / "results.csv").read_text()
    assert f"policy:{tmp_path.name}/model" in rows
    with model.open("ab") as changed:  # another model under the same name
        changed.write(b"\0")
    refused = cli(*sweep)
    assert refused.returncode != 0 and "policy_sha256" in refused.stderr


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ([], "--pilot policy needs --policy MODEL.zip"),
        (["--policy", "missing.zip"], "/missing.zip: no such file"),
        (["--policy", "README.md"], "is not a Stable-Baselines3 model"),
        (["--policy", "{ppo}", "--resolution", "640x480"], "trained on 84x84 images"),
    ],
)
def test_a_policy_that_cannot_fly_is_refused_in_one_line_before_any_folder(
    arguments: list[str], message: str, ppo_file: Path, tmp_path: Path
):
    arguments = [a.replace("{ppo}", str(ppo_file)) for a in arguments]
    root = Path(__file__).resolve().parents[2]
    done = cli("run", "S1", "--pilot", "policy", *arguments, "--out", str(tmp_path / "runs"),
               cwd=root)  # fmt: skip
    assert done.returncode == 2
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists()


def test_a_model_that_does_not_see_a_cave_is_refused(tmp_path: Path):
    from stable_baselines3 import PPO

    PPO("MlpPolicy", "Pendulum-v1", n_steps=16, batch_size=16).save(tmp_path / "pendulum.zip")
    with pytest.raises(ConfigError, match="a cavenav policy sees a Dict of some of rgb"):
        PolicyPilot(tmp_path / "pendulum.zip")


class _FlatEyes(gym.Env):
    """A policy's world where 'rgb' is a vector of ten numbers, not an image."""

    observation_space = gym.spaces.Dict(
        {"rgb": gym.spaces.Box(0, 255, (10,), np.uint8),
         "d_top": gym.spaces.Box(0, 20, (1,), np.float32)}
    )  # fmt: skip
    action_space = gym.spaces.Box(-1, 1, (4,), np.float32)


def test_a_file_that_is_no_whole_cavenav_model_is_one_line(ppo_file: Path, tmp_path: Path):
    import zipfile

    from stable_baselines3 import PPO

    with zipfile.ZipFile(ppo_file) as model:
        members = {name: model.read(name) for name in model.namelist()}
    cases = {}
    cases["no-model.zip"] = {"notes.txt": b"not a model"}
    cases["no-data.zip"] = {k: v for k, v in members.items() if k != "data"}
    PPO("MlpPolicy", "Pendulum-v1", n_steps=16, batch_size=16).save(tmp_path / "other.zip")
    with zipfile.ZipFile(tmp_path / "other.zip") as other:  # another network's weights
        cases["other-weights.zip"] = {**members, "policy.pth": other.read("policy.pth")}
    for name, contents in cases.items():
        with zipfile.ZipFile(tmp_path / name, "w") as model:
            for member, data in contents.items():
                model.writestr(member, data)
    PPO("MultiInputPolicy", _FlatEyes(), n_steps=16, batch_size=16).save(tmp_path / "flat.zip")
    refusals = [
        ("no-model.zip", "holds no 'data' member"),
        ("no-data.zip", "holds no 'data' member"),
        ("other-weights.zip", "its weights do not fit its network"),
        ("flat.zip", "sees 'rgb' as Box(0, 255, (10,), uint8), not as an image"),
    ]
    for name, says in refusals:  # each was a traceback (AssertionError, RuntimeError, ...)
        with pytest.raises(ConfigError) as refused:
            PolicyPilot(tmp_path / name)
        message = str(refused.value)
        assert message.startswith(f"--policy {tmp_path / name}") and says in message
        assert "\n" not in message
