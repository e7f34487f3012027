"""The system prompt of SPEC section 3, rendered from text files and the configuration.

Every number in the prompt comes from where it is set once: the admissible sets from the
`ActionSpace` the reply parser validates against, the standoff and forward caps from
`Rules` (which the shield and the geometric pilot enforce), and the depth range and
field of view from the observations the prompt is sent with. Users may supply their own
template file; it is rendered with the same fields (see `PromptConfig.fields`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from cavenav.core.errors import ConfigError
from cavenav.core.types import DEFAULT_RULES, Cruise, Observation, Rules
from cavenav.motion.actions import DEFAULT_SPACE, ActionSpace
from cavenav.motion.energy import PowerModel
from cavenav.pilots.designs import DESIGNS, REPLAN_EVERY, TURN_DEG, Design, navigable_reach_m
from cavenav.sensors.camera import CameraIntrinsics
from cavenav.sensors.depth import DEPTH_RANGE_M

__all__ = ["STRUCTURED_SCHEMA", "Instruments", "PromptConfig", "render_repair", "render_system"]


@dataclass(frozen=True)
class PromptConfig:
    """Numbers and switches of the VLM pilot's prompt.

    Attributes:
        space: admissible magnitudes (shared with the parser).
        rules: standoff, forward caps inside it, and the no-forward distance.
        history: number of earlier observations sent (K; 0 allowed).
        system_file: a user's own system-prompt template instead of the packaged one.
        structured: ask for a JSON object with fixed keys (for servers with JSON schemas).
        map_image: send a top-down picture of the pilot's map with each current
            observation (`cavenav.safety.cave_map`), and explain it in the system prompt.
        map_span_m: how many metres across that picture is.
        energy: tell the model what its battery has left with each current observation,
            and what moves cost (`cavenav.motion.energy`): energy-aware prompting.
        design: how the model answers (`cavenav.pilots.designs.DESIGNS`): the paper's
            action string, the number of an arrow drawn on the image, or a waypoint.
        replan_every: with waypoints, the most steps the planner flies before the model
            is asked again.
    """

    space: ActionSpace = field(default_factory=lambda: DEFAULT_SPACE)
    rules: Rules = DEFAULT_RULES
    history: int = 2
    system_file: Path | None = None
    structured: bool = False
    map_image: bool = False
    map_span_m: float = 32.0
    energy: bool = False
    design: Design = "direct"
    replan_every: int = REPLAN_EVERY

    def __post_init__(self) -> None:
        if self.design not in DESIGNS:
            raise ConfigError(
                f"unknown --design '{self.design}'; choose one of {', '.join(DESIGNS)}"
            )
        if self.replan_every < 1:
            raise ConfigError(
                f"--replan-every {self.replan_every}: the planner must fly at least 1 step "
                "before the model is asked again"
            )

    def fields(
        self, depth_range: tuple[float, float] = DEPTH_RANGE_M, hfov_deg: float | None = None
    ) -> dict[str, str]:
        """The values a template may use, as text.

        Args:
            depth_range: (D_min, D_max) of the depth images sent, metres.
            hfov_deg: their horizontal field of view (default: SPEC section 2's camera).
        """
        space, rules = self.space, self.rules
        if hfov_deg is None:
            hfov_deg = CameraIntrinsics().hfov_deg

        def listing(values: tuple[float, ...]) -> str:
            return ", ".join(_num(v) for v in values if v)

        history = (
            f"The {self.history} most recent earlier observations, oldest first, each with "
            "the action you took after it."
            if self.history
            else "No earlier observations: decide from the current one alone."
        )
        return {
            "depth_min_m": _num(depth_range[0]),
            "depth_max_m": _num(depth_range[1]),
            "hfov_deg": f"{hfov_deg:.1f}",
            "history_text": history,
            "standoff_m": _num(rules.standoff_m),
            "slow_forward_text": "-".join(_num(v) for v in rules.slow_forward_m),
            "no_forward_within_m": _num(rules.no_forward_within_m),
            "forward_m": listing(space.forward_m),
            "lateral_m": listing(space.lateral_m),
            "yaw_deg": listing(space.yaw_deg),
            "vertical_min_m": _num(space.vertical_range_m[0]),
            "vertical_max_m": _num(space.vertical_range_m[1]),
            "map_span_m": _num(self.map_span_m),
            # a metre straight ahead at cruise, with two lamps
            "energy_per_m_wh": f"{PowerModel().straight_wh_per_m(Cruise().speed_m_s):.3f}",
            "reach_m": _num(navigable_reach_m(rules)),
            "turn_deg": _num(TURN_DEG),
            "replan_every": str(self.replan_every),
        }


def _num(value: float) -> str:
    return f"{value:g}"


def _template(name: str) -> str:
    return resources.files("cavenav.pilots").joinpath("prompts", name).read_text(encoding="utf-8")


def _render(template: str, fields: dict[str, str], source: str) -> str:
    try:
        return template.format(**fields)
    except (KeyError, IndexError, ValueError) as exc:
        raise ConfigError(
            f"prompt template {source}: cannot fill {exc}; available fields: "
            f"{', '.join(sorted(fields))} (write literal braces as {{{{ and }}}})"
        ) from None


@dataclass(frozen=True)
class Instruments:
    """What the observations say about the sensors beyond the paper's: the depth image's
    source and the imaging sonar, when there is one, and the colour of the cave's
    guideline, when there is one (the prompt then explains them)."""

    depth_source: str = "exact"
    sonar_kind: str | None = None
    sonar_range_m: float = 0.0
    sonar_beam_deg: float = 0.0
    sonar_aperture_deg: float = 0.0
    sonar_span_deg: float = 0.0
    guideline: str | None = None

    @classmethod
    def of(cls, observation: Observation) -> Instruments:
        sonar = observation.sonar
        if sonar is None:
            return cls(observation.depth_source, guideline=observation.guideline)
        bearings = sonar.bearings_deg
        span = float(bearings.max() - bearings.min()) if sonar.kind == "multibeam" else 360.0
        return cls(
            observation.depth_source, sonar.kind, sonar.range_m, sonar.beam_width_deg,
            sonar.aperture_deg, span, observation.guideline,
        )  # fmt: skip

    def fields(self) -> dict[str, str]:
        """The sonar section's fields (`prompts/sonar.md`)."""
        scanning = self.sonar_kind == "ping360"
        span = _num(self.sonar_span_deg)
        return {
            "sonar_name": "scanning imaging sonar (a Ping360)" if scanning
            else f"forward-looking multibeam imaging sonar ({span} degrees wide)",
            "sonar_shape": "a disc with you at its centre" if scanning
            else "a fan with you at its bottom point",
            "sonar_range_m": _num(self.sonar_range_m),
            "sonar_beam_deg": _num(self.sonar_beam_deg),
            "sonar_aperture_deg": _num(self.sonar_aperture_deg),
            "sonar_half_aperture_deg": _num(self.sonar_aperture_deg / 2),
            "sonar_scan_text": (
                "Its head turns, one beam at a time: each step shows only the part of its "
                "sector swept since the last, and the rest as it was when last swept, from "
                "where you were then."
            ) if scanning else "It sees its whole fan at every step.",
        }  # fmt: skip


def render_system(
    config: PromptConfig,
    depth_range: tuple[float, float] = DEPTH_RANGE_M,
    hfov_deg: float | None = None,
    instruments: Instruments | None = None,
) -> str:
    """The full system prompt (mission, inputs, strategy, chain of thought, reply format).

    Args:
        depth_range: the depth range of the images the prompt is sent with (the VLM
            pilot passes each observation's own).
        hfov_deg: their horizontal field of view, likewise.
        instruments: the depth camera's source and the sonar, likewise: a stereo
            camera's and a sonar's sections follow the paper's prompt when present, and
            so does the cave line's (``prompts/guideline.md``) where the cave has one.

    The closing sections, how the model answers, are the design's (``config.design``,
    `cavenav.pilots.designs`): ``prompts/direct.md``, ``arrows.md`` or ``waypoint.md``
    after the shared ones. A user's own template is the whole prompt, whatever the design.
    """
    fields = config.fields(depth_range, hfov_deg)
    if config.system_file is not None:
        path = Path(config.system_file)
        if not path.is_file():
            raise ConfigError(f"prompt file not found: {path}")
        text = _render(path.read_text(encoding="utf-8"), fields, str(path))
    else:
        text = _render(_template("system.md"), fields, "system.md")
        design = f"{config.design}.md"
        text += "\n" + _render(_template(design), fields, design)
    instruments = instruments or Instruments()
    if instruments.depth_source == "stereo":
        text += "\n\n" + _template("stereo.md")
    if instruments.sonar_kind is not None:
        text += "\n\n" + _render(_template("sonar.md"), instruments.fields(), "sonar.md")
    if instruments.guideline is not None:
        line = {"guideline_colour": instruments.guideline}
        text += "\n\n" + _render(_template("guideline.md"), line, "guideline.md")
    if config.map_image:
        text += "\n\n" + _render(_template("map.md"), fields, "map.md")
    if config.energy:
        text += "\n\n" + _render(_template("energy.md"), fields, "energy.md")
    if config.structured:
        answer = {"direct": "the action string", "arrows": "the arrow's number"}
        chosen = answer.get(config.design, "your point or candidate's number")
        text += "\n\n" + _render(_template("structured.md"), {"answer": chosen}, "structured.md")
    return text


def render_repair(config: PromptConfig, reason: str) -> str:
    """The message that re-queries the model after an unusable reply, with the reason and
    the form the design's answer takes (`prompts/repair.md`, `<design>_repair.md`)."""
    name = "repair.md" if config.design == "direct" else f"{config.design}_repair.md"
    return _render(_template(name), {**config.fields(), "reason": reason}, name)


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
