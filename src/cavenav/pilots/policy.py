"""The learned pilot: a policy trained on the Gymnasium environment, flown like any other.

A Stable-Baselines3 model file (the ``.zip`` that ``model.save`` writes, from PPO, SAC or
any algorithm whose policy maps the environment's observation to a vector action, as
``examples/train_ppo.py`` trains one) becomes a `Pilot`: `cavenav run --pilot policy
--policy MODEL.zip`, a sweep and `cavenav compare` then treat it as they treat the VLM.

The policy sees what it saw in training: the keys of ``cavenav/CaveNav-vector-v0``'s
observation that its model names (any of rgb, depth, depth_m, d_top, d_bottom), built
from the `Observation` exactly as `cavenav.sim.env.CaveNavEnv` builds them, at the camera
size it was trained at (the command line sets ``--resolution`` to it). Its action is
taken deterministically (the mean, not a draw) and snapped to the admissible moves by
`cavenav.motion.actions.snap_action`, as the environment does. A policy whose action box is not
the environment's (``[-1, 1]``, as ``gymnasium.wrappers.RescaleAction`` trains it) is
read as that box mapped linearly onto the environment's.

Loading a model file runs Python's unpickler on it, as Stable-Baselines3 does: fly only
models you trust. Needs ``pip install 'cavenav[learn]'`` (Stable-Baselines3 and torch).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cavenav.core.errors import ConfigError, DependencyError, PilotFailure
from cavenav.core.types import Decision, Observation
from cavenav.motion.actions import (
    DEFAULT_SPACE,
    ActionSpace,
    action_bounds,
    format_action,
    snap_action,
)

__all__ = ["LoadedPolicy", "PolicyPilot", "load_policy", "policy_label"]

# The observation keys a policy may see (`cavenav.sim.env.CaveNavEnv.observation_space`).
KEYS = ("rgb", "depth", "depth_m", "d_top", "d_bottom")


@dataclass(frozen=True)
class LoadedPolicy:
    """A model file's policy, in evaluation mode, and what it expects.

    Attributes:
        policy: the Stable-Baselines3 policy (a ``torch.nn.Module`` with ``predict``).
        observation_space: the ``Dict`` space it was trained on.
        low, high: its action box, float64 (4,).
        image_size: (width, height) of the images it sees.
        limits: the depth and sounder ranges its spaces were saved with (inf for what it
            does not see), as `Observation.arrays` takes them.
    """

    policy: Any
    observation_space: Any
    low: np.ndarray
    high: np.ndarray
    image_size: tuple[int, int]
    limits: tuple[float, float]


@functools.cache
def load_policy(path: Path) -> LoadedPolicy:
    """The policy in the Stable-Baselines3 model file ``path``, checked against what a
    cavenav observation and action are (loaded once per process and path).

    Raises:
        ConfigError: the file is missing or not a model, or its policy sees keys a cavenav
            observation lacks, sees no image, or does not act with four numbers.
        DependencyError: Stable-Baselines3 is not installed.
    """
    try:
        from stable_baselines3.common.save_util import load_from_zip_file
    except ImportError:
        raise DependencyError(
            "--pilot policy needs Stable-Baselines3: pip install 'cavenav[learn]'"
        ) from None
    if not path.is_file():
        raise ConfigError(f"--policy {path}: no such file (a model saved by Stable-Baselines3)")
    try:
        data, params, _ = load_from_zip_file(path, device="cpu")
    except Exception as exc:  # a zip that is not a model fails in many ways
        raise ConfigError(f"--policy {path} is not a Stable-Baselines3 model: {exc}") from None
    wanted = ("observation_space", "action_space", "policy_class")
    if not data or any(key not in data for key in wanted) or "policy" not in (params or {}):
        raise ConfigError(
            f"--policy {path} is not a Stable-Baselines3 model: it holds no "
            + ("'data' member" if not data else "policy, or no observation or action space")
        )
    observations, actions = data["observation_space"], data["action_space"]
    _check_spaces(path, observations, actions)
    kwargs = dict(data.get("policy_kwargs") or {})
    kwargs.pop("device", None)
    if data.get("use_sde") and "use_sde" not in kwargs:  # on-policy algorithms keep it apart
        kwargs["use_sde"] = True
    policy = data["policy_class"](observations, actions, lambda _: 0.0, **kwargs)
    try:
        policy.load_state_dict(params["policy"])
    except RuntimeError as exc:  # weights of another network: torch lists every mismatch
        first = str(exc).splitlines()[0].rstrip(":")
        raise ConfigError(
            f"--policy {path}: its weights do not fit its network ({first})"
        ) from None
    policy.set_training_mode(False)
    seen = observations.spaces
    image = next(seen[k] for k in ("rgb", "depth", "depth_m") if k in seen)

    def high(key: str) -> float:
        return float(seen[key].high.max()) if key in seen else math.inf

    return LoadedPolicy(
        policy,
        observations,
        np.asarray(actions.low, np.float64),
        np.asarray(actions.high, np.float64),
        _image_size(image),
        (high("depth_m"), min(high("d_top"), high("d_bottom"))),
    )


def _image_size(space: Any) -> tuple[int, int]:  # noqa: ANN401
    """(width, height) of an image space: Stable-Baselines3 saves a uint8 image's space
    channels first (its CNN's order) and transposes what it is given to match."""
    from stable_baselines3.common.preprocessing import (
        is_image_space,
        is_image_space_channels_first,
    )

    shape = space.shape
    if is_image_space(space) and is_image_space_channels_first(space):
        return int(shape[2]), int(shape[1])
    return int(shape[1]), int(shape[0])


def _check_spaces(path: Path, observations: Any, actions: Any) -> None:  # noqa: ANN401
    keys = list(getattr(observations, "spaces", {}))
    if not keys or any(k not in KEYS for k in keys):
        raise ConfigError(
            f"--policy {path} sees {keys or observations}; a cavenav policy sees a Dict of "
            f"some of {', '.join(KEYS)} (cavenav/CaveNav-vector-v0's observation)"
        )
    images = [k for k in ("rgb", "depth", "depth_m") if k in keys]
    if not images:
        raise ConfigError(f"--policy {path} sees no image (it sees {', '.join(keys)})")
    flat = [k for k in images if len(getattr(observations.spaces[k], "shape", ())) not in (2, 3)]
    if flat:
        raise ConfigError(
            f"--policy {path} sees '{flat[0]}' as {observations.spaces[flat[0]]}, not as an "
            "image (height x width, with or without channels)"
        )
    shape, low = getattr(actions, "shape", None), getattr(actions, "low", None)
    if shape != (4,) or low is None or not np.isfinite([actions.low, actions.high]).all():
        raise ConfigError(
            f"--policy {path} acts in {actions}; a cavenav policy acts with a bounded Box "
            "of four numbers (df, dr, dz, dpsi)"
        )


def policy_label(path: str | Path) -> str:
    """``policy:FOLDER/FILE`` (no suffix): the name tables and records give a model file,
    its folder included, since training writes ``best.zip`` in every run's folder."""
    path = Path(path)
    return f"policy:{path.parent.name}/{path.stem}" if path.parent.name else f"policy:{path.stem}"


class PolicyPilot:
    """Flies a learned policy: each observation in, its deterministic action out."""

    def __init__(self, path: Path, space: ActionSpace = DEFAULT_SPACE):
        self.path, self.space = Path(path), space
        self.name = policy_label(path)
        self.loaded = load_policy(self.path.absolute())
        self._bounds = action_bounds(space).astype(np.float64)

    def reset(self) -> None:
        """Nothing to forget: the policy answers each observation alone."""

    def _seen(self, observation: Observation) -> dict[str, np.ndarray]:
        """The observation as the environment gives it to a learner (`Observation.arrays`,
        at the limits the policy's spaces were saved with), the policy's keys."""
        arrays = observation.arrays(*self.loaded.limits)
        return {key: arrays[key] for key in self.loaded.observation_space.spaces}

    def decide(self, observation: Observation) -> Decision:
        width, height = self.loaded.image_size
        if observation.rgb.shape[:2] != (height, width):
            raise PilotFailure(
                f"the policy {self.path} sees {width}x{height} images, the camera gives "
                f"{observation.rgb.shape[1]}x{observation.rgb.shape[0]} (--resolution)"
            )
        output, _ = self.loaded.policy.predict(self._seen(observation), deterministic=True)
        output = np.asarray(output, np.float64).reshape(4)
        low, high = self.loaded.low, self.loaded.high
        vector = -self._bounds + (output - low) * 2.0 * self._bounds / (high - low)
        action = snap_action(vector, self.space)
        numbers = ", ".join(f"{v:.3g}" for v in vector)
        why = (
            f"policy {self.path.name}: (df, dr, dz, dpsi) = ({numbers}), "
            "snapped to the admissible moves"
        )
        return Decision(
            action=action, action_text=format_action(action), justification=why, raw=why
        )
