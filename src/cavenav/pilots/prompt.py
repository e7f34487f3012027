"""The system prompt of SPEC section 3, rendered from text files and the configuration.

Every number in the prompt (standoff, forward caps, admissible sets, depth range) comes
from `PromptConfig`, the same object the reply parser validates against, so the prompt
and the parser cannot drift apart. Users may supply their own template file; it is
rendered with the same fields (see `PromptConfig.fields`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from cavenav.actions import DEFAULT_SPACE, ActionSpace
from cavenav.errors import ConfigError

__all__ = ["STRUCTURED_SCHEMA", "PromptConfig", "render_repair", "render_system"]


@dataclass(frozen=True)
class PromptConfig:
    """Numbers and switches of the VLM pilot's prompt.

    Attributes:
        space: admissible magnitudes (shared with the parser).
        standoff_m: desired distance to every surface.
        slow_forward_m: forward range allowed inside the standoff (SPEC: 0.1-0.2 m).
        no_forward_within_m: obstacle range ahead below which forward motion is forbidden.
        depth_min_m, depth_max_m: the depth PNG's range, explained to the model.
        hfov_deg: horizontal field of view of both forward images.
        history: number of earlier observations sent (K; 0 allowed).
        system_file: a user's own system-prompt template instead of the packaged one.
        structured: ask for a JSON object with fixed keys (for servers with JSON schemas).
    """

    space: ActionSpace = field(default_factory=lambda: DEFAULT_SPACE)
    standoff_m: float = 2.0
    slow_forward_m: tuple[float, float] = (0.1, 0.2)
    no_forward_within_m: float = 1.5
    depth_min_m: float = 0.0
    depth_max_m: float = 20.0
    hfov_deg: float = 53.13
    history: int = 2
    system_file: Path | None = None
    structured: bool = False

    def fields(self) -> dict[str, str]:
        """The values a template may use, as text."""
        space = self.space

        def listing(values: tuple[float, ...]) -> str:
            return ", ".join(_num(v) for v in values if v)

        history = (
            f"The {self.history} most recent earlier observations, oldest first, each with "
            "the action you took after it."
            if self.history
            else "No earlier observations: decide from the current one alone."
        )
        return {
            "depth_min_m": _num(self.depth_min_m),
            "depth_max_m": _num(self.depth_max_m),
            "hfov_deg": f"{self.hfov_deg:.1f}",
            "history_text": history,
            "standoff_m": _num(self.standoff_m),
            "slow_forward_text": "-".join(_num(v) for v in self.slow_forward_m),
            "no_forward_within_m": _num(self.no_forward_within_m),
            "forward_m": listing(space.forward_m),
            "lateral_m": listing(space.lateral_m),
            "yaw_deg": listing(space.yaw_deg),
            "vertical_min_m": _num(space.vertical_range_m[0]),
            "vertical_max_m": _num(space.vertical_range_m[1]),
        }


def _num(value: float) -> str:
    return f"{value:g}"


def _template(name: str) -> str:
    return resources.files("cavenav.pilots").joinpath("prompts", name).read_text(encoding="utf-8")


def _render(template: str, config: PromptConfig, source: str, **extra: str) -> str:
    try:
        return template.format(**config.fields(), **extra)
    except (KeyError, IndexError, ValueError) as exc:
        raise ConfigError(
            f"prompt template {source}: cannot fill {exc}; available fields: "
            f"{', '.join(sorted(config.fields()))} (write literal braces as {{{{ and }}}})"
        ) from None


def render_system(config: PromptConfig) -> str:
    """The full system prompt (mission, inputs, strategy, chain of thought, reply format)."""
    if config.system_file is not None:
        path = Path(config.system_file)
        if not path.is_file():
            raise ConfigError(f"prompt file not found: {path}")
        text = _render(path.read_text(encoding="utf-8"), config, str(path))
    else:
        text = _render(_template("system.md"), config, "system.md")
    if config.structured:
        text += "\n\n" + _template("structured.md")
    return text


def render_repair(config: PromptConfig, reason: str) -> str:
    """The message that re-queries the model after an unusable reply, with the reason."""
    return _render(_template("repair.md"), config, "repair.md", reason=reason)


# The fixed-key JSON schema of structured-output mode: OpenAI strict schemas cannot express
# "a dict with one free key", so the reply parser turns these keys into the one pair.
STRUCTURED_SCHEMA = {
    "type": "object",
    "properties": {
        key: {"type": "string"} for key in ("situation", "constraints", "action", "justification")
    },
    "required": ["situation", "constraints", "action", "justification"],
    "additionalProperties": False,
}
