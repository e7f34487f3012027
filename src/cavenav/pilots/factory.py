"""Pilots by name: a plain, picklable description that builds the pilot where it flies.

The command line, the sweep workers (other processes, other machines) and the report all
need "which pilot, with which settings" as data: `PilotSpec` is that data, JSON-able for
sweep.json, and `PilotSpec.build` makes the pilot in the process that will fly it, so a
model client or a loaded model never has to travel between processes.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from cavenav.core.errors import ConfigError
from cavenav.pilots.base import Pilot
from cavenav.pilots.designs import REPLAN_EVERY, design_suffix
from cavenav.pilots.endpoints import OpenAIConfig, TransformersConfig
from cavenav.pilots.prompt import PromptConfig
from cavenav.pilots.reply import MAX_REQUERIES
from cavenav.pilots.request_images import ImageEncoding

__all__ = ["PILOTS", "PilotSpec", "VLMOptions"]

PILOTS = ("geometric", "vlm", "replay", "random", "policy")
# In a model folder `cavenav finetune` wrote: how the model must be asked (the prompt and
# image settings it learned with), and its own system prompt, if it has one.
PILOT_SETTINGS = "cavenav_pilot.json"
PROMPT_FILE = "cavenav_prompt.md"
# Pilots that can fly in another's shadow (`--teacher`): those that need no settings.
TEACHERS = ("geometric", "random")


@dataclass(frozen=True)
class VLMOptions:
    """How to reach the model and how to prompt it (the `--...` flags of the VLM pilot).

    Each field is a flag of `cavenav run`, `eval` and `fly`, declared with its help in
    `cavenav.cli.episode_flags.VLM` and defaulting to the value here; a field without a flag
    there fails a test.

    Holds the *name* of the environment variable with the API key, never the key, so it
    can be written to sweep.json and run folders.
    """

    model: str | None = None
    backend: str = "openai"  # or "transformers"
    base_url: str | None = None
    api_key_env: str = OpenAIConfig.api_key_env
    timeout: float = OpenAIConfig.timeout_s  # seconds one attempt may take, whole
    deadline: float | None = OpenAIConfig.deadline_s  # a request's, retries included
    retries: int = OpenAIConfig.max_retries
    temperature: float = OpenAIConfig.temperature
    max_tokens: int = OpenAIConfig.max_tokens
    detail: str | None = None
    requeries: int = MAX_REQUERIES
    history: int = PromptConfig.history
    prompt_file: str | None = None
    structured: bool = False
    map_image: bool = False  # a top-down picture of the pilot's map with each step
    energy_prompt: bool = False  # tell the model its battery's energy left
    design: str = "direct"  # how the model answers: direct, arrows or waypoint
    replan_every: int = REPLAN_EVERY  # waypoint: the planner's most steps between answers
    image_format: str = "png"  # how the colour image is sent: png or jpeg
    jpeg_quality: int = 90
    image_size: str | None = None  # "WxH": the images are resized to it before sending
    price: str | None = None  # "input,output" USD per million tokens
    cache: str | None = None  # reply cache folder
    device: str = "auto"  # transformers only

    def prices(self) -> tuple[float, float] | None:
        if not self.price:
            return None
        try:
            price_in, price_out = (float(v) for v in self.price.split(","))
        except ValueError:
            raise ConfigError(
                f"--price must be 'input,output' in USD per million tokens, got '{self.price}'"
            ) from None
        if not all(math.isfinite(v) and v >= 0 for v in (price_in, price_out)):
            raise ConfigError(
                f"--price '{self.price}': each part is a finite number of USD, 0 or more"
            )
        return price_in, price_out

    def for_model(self) -> VLMOptions:
        """These options with the prompt and image settings the model folder says it must
        be asked with (`PILOT_SETTINGS`, written by `cavenav finetune`), its own prompt
        file among them; unchanged for any other model.

        Raises:
            ConfigError: the folder's settings cannot be read.
        """
        folder = Path(self.model or "")
        path = folder / PILOT_SETTINGS
        if not self.model or not path.is_file():
            return self
        try:
            prompt = dict(json.loads(path.read_text(encoding="utf-8"))["prompt"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"{path} cannot be read: {exc}") from None
        known = {f.name for f in fields(VLMOptions)}
        given = {key: value for key, value in prompt.items() if key in known}
        if given.get("prompt_file"):
            given["prompt_file"] = str(folder / given["prompt_file"])
        return replace(self, **given)

    def prompt_config(self) -> PromptConfig:
        """The prompt these options ask for (`cavenav.pilots.prompt.PromptConfig`)."""
        return PromptConfig(
            history=self.history,
            system_file=Path(self.prompt_file) if self.prompt_file else None,
            structured=self.structured,
            map_image=self.map_image,
            energy=self.energy_prompt,
            design=self.design,  # type: ignore[arg-type]  # checked by PromptConfig
            replan_every=self.replan_every,
        )

    def request_images(self) -> ImageEncoding:
        """How the observations' images travel (`cavenav.pilots.request_images`).

        Raises:
            ConfigError: an unknown format, a quality outside 1-100 or a size that is not
                WIDTHxHEIGHT.
        """
        from cavenav.sensors.camera import parse_resolution

        size = parse_resolution(self.image_size, "--image-size") if self.image_size else None
        return ImageEncoding(self.image_format, self.jpeg_quality, size)  # type: ignore[arg-type]


@dataclass(frozen=True)
class PilotSpec:
    """Which pilot flies, with which settings.

    Attributes:
        name: one of `PILOTS`.
        vlm: the model settings of the VLM pilot.
        recording: the run folder the replay pilot re-flies.
        policy: the model file the policy pilot flies (`cavenav.pilots.policy`).
        policy_sha256: that file's digest as a sweep recorded it; None to read the file's.
        teacher: a pilot from `TEACHERS` that decides alongside at every step, its answer
            recorded with the step (`cavenav.pilots.shadow`: DAgger's relabelling); None:
            none.
    """

    name: str = "geometric"
    vlm: VLMOptions = field(default_factory=VLMOptions)
    recording: str | None = None
    policy: str | None = None
    policy_sha256: str | None = None
    teacher: str | None = None

    def __post_init__(self) -> None:
        if self.name not in PILOTS:
            raise ConfigError(f"unknown pilot '{self.name}'; choose one of {', '.join(PILOTS)}")
        if self.name == "vlm" and not self.vlm.model:
            raise ConfigError(
                "the VLM pilot needs --model (a model name, or a folder for transformers)"
            )
        if self.name == "replay" and self.recording is None:
            raise ConfigError("--pilot replay needs --from RUN_DIR")
        if self.name == "policy" and self.policy is None:
            raise ConfigError("--pilot policy needs --policy MODEL.zip (a Stable-Baselines3 model)")
        if self.teacher is not None and self.teacher not in TEACHERS:
            raise ConfigError(
                f"unknown teacher '{self.teacher}'; choose one of {', '.join(TEACHERS)}"
            )
        self.vlm.prices()  # a malformed setting fails now, not in a worker
        self.vlm.request_images()
        self.vlm.prompt_config()

    @property
    def label(self) -> str:
        """The name tables and run folders show: ``vlm:MODEL`` for model pilots (``vlm:MODEL
        (arrows)`` and ``(waypoint)`` for the other designs), ``policy:FOLDER/FILE`` (no
        suffix) for learned ones."""
        if self.name == "vlm":
            return f"vlm:{self.vlm.model}{design_suffix(self.vlm.design)}"
        if self.name == "policy":
            from cavenav.pilots.policy import policy_label

            return policy_label(str(self.policy))
        return self.name

    def image_size(self) -> tuple[int, int] | None:
        """The (width, height) of the images this pilot must see, where it was trained
        at one size (the policy pilot); None where any camera will do."""
        if self.name != "policy":
            return None
        from cavenav.pilots.policy import load_policy

        return load_policy(Path(str(self.policy)).absolute()).image_size

    def to_dict(self) -> dict[str, Any]:
        """The settings that change what the pilot does (for sweep.json)."""
        out: dict[str, Any] = {"name": self.name, "label": self.label}
        if self.name == "vlm":
            out["options"] = asdict(self.vlm)
        if self.recording is not None:
            out["recording"] = self.recording
        if self.policy is not None:  # and which model it held, should the file be replaced
            out["policy"] = self.policy
            digest = self.policy_sha256
            if digest is None and Path(self.policy).is_file():
                digest = hashlib.sha256(Path(self.policy).read_bytes()).hexdigest()
            if digest is not None:
                out["policy_sha256"] = digest
        if self.teacher is not None:  # absent otherwise, as before teachers existed
            out["teacher"] = self.teacher
        return out

    def build(self, seed: int = 0, check: bool = True) -> Pilot:
        """Make the pilot, in the shadow of its teacher if it has one; ``seed`` seeds the
        random pilot's draws (a random teacher's too).

        Args:
            check: let a model pilot verify its backend (key, server) right away.
        """
        pilot = self._build(seed, check)
        if self.teacher is None:
            return pilot
        from cavenav.pilots.shadow import ShadowedPilot

        return ShadowedPilot(pilot, PilotSpec(self.teacher).build(seed))

    def _build(self, seed: int, check: bool) -> Pilot:
        if self.name == "geometric":
            from cavenav.pilots.geometric import GeometricPilot

            return GeometricPilot()
        if self.name == "random":
            from cavenav.pilots.random_pilot import RandomPilot

            return RandomPilot(seed)
        if self.name == "replay":
            from cavenav.pilots.replay import ReplayPilot

            return ReplayPilot(Path(str(self.recording)))
        if self.name == "policy":
            from cavenav.pilots.policy import PolicyPilot

            return PolicyPilot(Path(str(self.policy)))
        return _vlm_pilot(self.vlm, check)


def _vlm_pilot(options: VLMOptions, check: bool) -> Pilot:
    from cavenav.pilots.backends import CachedBackend, OpenAIBackend, TransformersBackend
    from cavenav.pilots.vlm import VLMPilot

    assert options.model is not None
    engine: Any
    if options.backend == "openai":
        engine = OpenAIBackend(
            OpenAIConfig(
                model=options.model,
                base_url=options.base_url,
                api_key_env=options.api_key_env,
                timeout_s=options.timeout,
                deadline_s=options.deadline,
                max_retries=options.retries,
                temperature=options.temperature,
                max_tokens=options.max_tokens,
                detail=options.detail or OpenAIConfig.detail,
            )
        )
    elif options.backend == "transformers":
        engine = TransformersBackend(
            TransformersConfig(
                model=options.model,
                device=options.device,
                max_new_tokens=options.max_tokens,
                temperature=options.temperature,
            )
        )
    else:
        raise ConfigError(f"unknown backend '{options.backend}'; use openai or transformers")
    if options.cache is not None:
        engine = CachedBackend(engine, Path(options.cache))
    return VLMPilot(
        engine,
        options.prompt_config(),
        max_requeries=options.requeries,
        detail=options.detail,
        price_per_mtok=options.prices(),
        check=check,
        images=options.request_images(),
    )
