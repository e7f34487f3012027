"""A recorded episode flown again to ask, at each step, what the VLM pilot would be asked.

Sweeps fly without frames, and a request is more than a frame anyway: the system prompt,
the K earlier observations with the actions executed after them, the images in the
format and size the pilot sends. So a run folder's requests are made again here, exactly:

- the cave is rebuilt from its name, seed and difficulty, and the episode's
  `EpisodeConfig` from summary.json, where every run folder records it whole;
- the environment is reset with the recorded seed and steps through the recorded
  (executed) actions, so the sensor noise, the marine snow and the silt come out as
  they did;
- at each step a `VLMPilot` decides on the observation, its model a script that answers
  with the step's target reply and keeps the request it was sent: the pilot's own code
  builds the request, so it is the request the pilot would have sent.

Every step's pose is checked against the record. An episode that does not fly again
where it flew (another cavenav version, a changed cave) is refused, never guessed at.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

from cavenav.core.errors import CavenavError, ConfigError, PilotFailure
from cavenav.episode.loop import make_env
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.backends import Completion, Message
from cavenav.pilots.factory import VLMOptions
from cavenav.pilots.vlm import VLMPilot
from cavenav.world.scenarios import SCENARIOS, Difficulty, Scenario, load_scenario

__all__ = ["recorded_config", "recorded_requests"]

# steps.jsonl rounds positions to 0.1 mm and headings to 0.001 degree.
_POSITION_TOLERANCE_M = 2e-4
_YAW_TOLERANCE_DEG = 2e-3


def recorded_config(summary: Mapping[str, Any]) -> EpisodeConfig:
    """The `EpisodeConfig` an episode flew with, from its summary.json ("config").

    Raises:
        ConfigError: the summary holds no configuration, or one this version cannot read.
    """
    data = summary.get("config")
    if not isinstance(data, Mapping):
        raise ConfigError("its summary.json records no episode configuration")
    try:
        return _rebuilt(EpisodeConfig, data)
    except (TypeError, ValueError, CavenavError) as exc:
        raise ConfigError(f"its episode configuration cannot be read: {exc}") from None


def _rebuilt(kind: type, data: Mapping[str, Any]) -> Any:  # noqa: ANN401 - any dataclass
    """A dataclass from its `dataclasses.asdict` JSON: nested dataclasses and tuples
    (JSON's lists) restored by the fields' types; absent fields keep their defaults."""
    hints = typing.get_type_hints(kind)
    given = {f.name: _value(hints[f.name], data[f.name]) for f in dataclasses.fields(kind)
             if f.init and f.name in data}  # fmt: skip
    return kind(**given)


def _value(kind: Any, value: Any) -> Any:  # noqa: ANN401 - any field's type and value
    """``value`` as a field of type ``kind`` holds it."""
    options = typing.get_args(kind) if _is_union(kind) else (kind,)
    for option in options:
        if isinstance(value, Mapping) and dataclasses.is_dataclass(option):
            return _rebuilt(option, value)  # type: ignore[arg-type]
        if isinstance(value, list) and typing.get_origin(option) is tuple:
            inner = typing.get_args(option)
            if len(inner) == 2 and inner[1] is Ellipsis:
                return tuple(_value(inner[0], item) for item in value)
            return tuple(_value(k, item) for k, item in zip(inner, value, strict=True))
    return value


def _is_union(kind: Any) -> bool:  # noqa: ANN401
    return typing.get_origin(kind) in (typing.Union, types.UnionType)


def recorded_cave(scenario: str, summary: Mapping[str, Any]) -> Scenario:
    """The cave an episode flew: ``scenario`` (a family, or the scenario file a sweep
    names) with the recorded seed and difficulty, checked against the recorded mesh.

    Raises:
        ConfigError: a run folder of a scenario file flown alone (its path is not
            recorded), or a cave that no longer comes out as it was.
    """
    if scenario not in SCENARIOS and not scenario.lower().endswith(".toml"):
        raise ConfigError(
            f"its cave '{scenario}' is not a family and its scenario file is not recorded; "
            "fly it in a sweep (cavenav eval --scenarios FILE) to make training data of it"
        )
    knobs = summary.get("difficulty") or {}
    cave = load_scenario(scenario, summary.get("seed") or 0, difficulty=Difficulty.from_dict(knobs))
    if cave.mesh.name != summary.get("mesh"):
        raise ConfigError(
            f"its cave comes out as {cave.mesh.name}, not the {summary.get('mesh')} it flew"
        )
    return cave


@dataclass
class _Script:
    """The model of the pilot that asks: answers with ``reply``, keeps what it was sent."""

    reply: str = ""
    sent: list[Message] | None = None
    name: str = "script"
    model: str = "script"

    def check(self) -> None:
        """Nothing to reach."""

    def complete(self, messages: list[Message], json_schema: dict | None = None) -> Completion:
        self.sent = messages
        return Completion(self.reply)


def recorded_requests(
    cave: Scenario,
    config: EpisodeConfig,
    steps: Sequence[Mapping[str, Any]],
    replies: Sequence[str],
    options: VLMOptions,
) -> Iterator[list[Message]]:
    """The request the VLM pilot set up by ``options`` would send at each of ``steps``.

    Args:
        cave: the cave the episode flew.
        config: the configuration it flew with.
        steps: the recorded steps that flew an action (steps.jsonl), in order.
        replies: the reply each step's request is answered with (the target): it tells
            the pilot's history which action came next, where a step does not say.

    Raises:
        ConfigError: a step that does not fly again where it was recorded, or a reply
            the pilot cannot read.
    """
    flown = replace(config, shield=False, stuck_after=None, max_steps=len(steps) + 1)
    env = make_env(cave, flown)
    script = _Script()
    pilot = VLMPilot(
        script,
        options.prompt_config(),
        max_requeries=0,
        detail=options.detail,
        check=False,
        images=options.request_images(),
    )
    try:
        _, info = env.reset(seed=config.seed)
        for step, reply in zip(steps, replies, strict=True):
            _same_pose(step, info["vehicle_pose"])
            script.reply = reply
            try:
                pilot.decide(info["observation"])
            except PilotFailure as failure:
                raise ConfigError(
                    f"step {step['step']}: its target reply cannot be read: {failure}"
                ) from None
            assert script.sent is not None
            yield script.sent
            _, _, _, _, info = env.step(step["action"])
    finally:
        env.close()


def _same_pose(step: Mapping[str, Any], pose: Any) -> None:  # noqa: ANN401 - a Pose
    """Refuse a step that the episode flown again reaches elsewhere than recorded."""
    recorded = step["pose"]
    off = math.dist((pose.x, pose.y, pose.z), (recorded["x"], recorded["y"], recorded["z"]))
    turned = abs((pose.yaw_deg - recorded.get("yaw_deg", 0.0) + 180.0) % 360.0 - 180.0)
    if off > _POSITION_TOLERANCE_M or turned > _YAW_TOLERANCE_DEG:
        raise ConfigError(
            f"step {step['step']} does not fly again where it was recorded ({off:.4f} m, "
            f"{turned:.3f} deg away): it was flown by another version or in another cave"
        )
