"""The VLM pilot of SPEC sections 3-4: prompt, images, chain of thought, bounded re-query.

Per step it sends the fixed system prompt first (servers with prefix caching reuse it),
then the K most recent earlier observations with the action taken after each, then the
current RGB and depth images with d_top and d_bottom. A reply that cannot be used is sent
back with the reason, at most `max_requeries` times; after that, or when the backend
gives up after its own retries (or is refused the key), the pilot raises `PilotFailure`,
the failed request recorded with it, and the episode ends as ``pilot_failure``. It never
substitutes a default action.

How the model answers is its design (`cavenav.pilots.designs`): the paper's action string
(``direct``, the default, whose requests are byte for byte those of earlier versions), or
a number or a point among choices drawn on the colour image (``arrows``, ``waypoint``),
which the pilot's `Helm` turns into moves; with waypoints, its planner flies the steps
between the model's answers without asking it.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import numpy as np

from cavenav.core.errors import ActionError, BackendAuthError, BackendError, PilotFailure
from cavenav.core.types import Action, Decision, Observation, Usage
from cavenav.motion.actions import format_action
from cavenav.pilots.backends import Backend, Completion, Message, request_hash
from cavenav.pilots.designs import Choice, Helm, design_suffix, read_choice
from cavenav.pilots.prompt import (
    STRUCTURED_SCHEMA,
    Instruments,
    PromptConfig,
    render_repair,
    render_system,
)
from cavenav.pilots.reply import MAX_REQUERIES, final_answer, parse_reply
from cavenav.pilots.request_images import PNG, ImageEncoding, data_url, remember_drawing
from cavenav.safety.cave_map import CaveMap
from cavenav.safety.reckoning import executed_since

__all__ = ["EncodedObservation", "Exchange", "VLMPilot", "build_messages", "png_data_url"]

Parsed = TypeVar("Parsed")


def png_data_url(image: np.ndarray) -> str:
    """An (H, W) or (H, W, 3) uint8 image as a PNG data URL, encoded once
    (`cavenav.pilots.request_images.data_url`)."""
    return data_url(image)


@dataclass(frozen=True)
class EncodedObservation:
    """An observation as sent: encoded images, sounder readings, action taken after it.

    ``depth_url`` is None when the observation has no depth image (a photograph), and
    a sounder reading NaN when it was not measured; the request then says so in words.
    """

    rgb_url: str
    depth_url: str | None
    d_top: float
    d_bottom: float
    action: str = ""
    sonar_url: str | None = None  # the current observation's sonar image; never history's


@dataclass(frozen=True)
class Exchange:
    """One request and its reply, for the run folder (images are stored by hash there)."""

    messages: list[Message]
    completion: Completion
    error: str | None = None  # why the reply was rejected, if it was

    @classmethod
    def failed(cls, messages: list[Message], error: BackendError) -> Exchange:
        """A request the backend gave up on: whatever body came back, each failed
        attempt's error, and the give-up message as the reason it was rejected."""
        retries = max(len(error.errors) - 1, 0)  # one line per attempt
        completion = Completion(error.reply, retries=retries, errors=error.errors)
        return cls(list(messages), completion, str(error))

    def to_record(self, model: str) -> dict[str, Any]:
        """A plain JSON record: the episode layer stores it without knowing any backend."""
        completion = self.completion
        name = completion.model or model
        return {
            "request_sha256": request_hash(name, self.messages, {}),
            "messages": self.messages,
            "reply": completion.text,
            "rejected": self.error,
            "model": name,
            "prompt_tokens": completion.prompt_tokens,
            "completion_tokens": completion.completion_tokens,
            "latency_s": round(completion.latency_s, 4),
            "model_s": None if completion.model_s is None else round(completion.model_s, 4),
            "transport_retries": completion.retries,
            "transport_errors": list(completion.errors),
            "cached": completion.cached,
        }


def _image(url: str, detail: str | None) -> dict[str, Any]:
    image_url: dict[str, Any] = {"url": url}
    if detail:
        image_url["detail"] = detail
    return {"type": "image_url", "image_url": image_url}


# Said instead of a depth image that does not exist: a blank one would read as "nothing
# within D_max", and the system prompt promises a depth image with every observation.
NO_DEPTH_TEXT = "No depth image is available for this observation: judge distances from"


def _metres(value: float) -> str:
    return f"{value:.2f} m" if math.isfinite(value) else "unknown"


def _readings(seen: EncodedObservation) -> str:
    return f"d_top = {_metres(seen.d_top)}, d_bottom = {_metres(seen.d_bottom)}"


def _introduce(seen: EncodedObservation, opening: str, detail: str | None) -> list[dict[str, Any]]:
    """The sounder readings and what the images are, then the images."""
    text = f"{opening}: {_readings(seen)}."
    sonar = [] if seen.sonar_url is None else [_image(seen.sonar_url, detail)]
    then_sonar = ", then sonar" if sonar else ""
    if seen.depth_url is not None:
        return [
            {"type": "text", "text": f"{text} Colour, then depth{then_sonar}:"},
            _image(seen.rgb_url, detail),
            _image(seen.depth_url, detail),
            *sonar,
        ]
    sounders = math.isfinite(seen.d_top) or math.isfinite(seen.d_bottom)
    sources = "the colour image and the sounder readings" if sounders else "the colour image"
    return [
        {
            "type": "text",
            "text": f"{text} {NO_DEPTH_TEXT} {sources}. Colour{then_sonar}:",
        },
        _image(seen.rgb_url, detail),
        *sonar,
    ]


def build_messages(
    system: str,
    current: EncodedObservation,
    history: list[EncodedObservation],
    detail: str | None = None,
    map_view: tuple[str, str] | None = None,
    energy_left_wh: float | None = None,
    offered: str | None = None,
) -> list[Message]:
    """OpenAI-format messages: system prompt, then one user turn with every image.

    Each observation is introduced by its sounder readings ("unknown" where not
    measured) and by what its images are; one without a depth image gets a sentence
    saying so (`NO_DEPTH_TEXT`) in place of the image. ``map_view`` is the pilot's map
    as (a line of text, a picture's data URL), sent after the current images;
    ``energy_left_wh``, when given, what the battery has left, said after them;
    ``offered``, the numbered choices drawn on the colour image in words, last (the
    arrows and waypoint designs, `cavenav.pilots.designs`).
    """
    content: list[dict[str, Any]] = []
    for k, seen in enumerate(history):
        age = len(history) - k
        when = f"{age} step{'s' if age > 1 else ''} ago"
        content += [
            *_introduce(seen, f"Earlier observation ({when})", detail),
            {"type": "text", "text": f"Action taken after it: {seen.action}"},
        ]
    content += _introduce(current, "Current observation", detail)
    if map_view is not None:
        words, url = map_view
        content += [
            {"type": "text", "text": f"Your map (heading up). {words}"},
            _image(url, detail),
        ]
    if energy_left_wh is not None:
        content.append({"type": "text", "text": f"Battery: {energy_left_wh:.2f} Wh left."})
    if offered is not None:
        content.append({"type": "text", "text": offered})
    content.append(
        {"type": "text", "text": "Think step by step, then give the final one-pair dictionary."}
    )
    return [{"role": "system", "content": system}, {"role": "user", "content": content}]


class VLMPilot:
    """Steers with a vision-language model behind any `Backend`."""

    def __init__(
        self,
        backend: Backend,
        prompt: PromptConfig | None = None,
        max_requeries: int = MAX_REQUERIES,
        detail: str | None = None,
        price_per_mtok: tuple[float, float] | None = None,
        check: bool = True,
        images: ImageEncoding = PNG,
    ):
        """
        Args:
            backend: where the model runs.
            prompt: prompt numbers and switches (shared with the reply parser).
            max_requeries: re-queries after unusable replies before giving up (SPEC: N).
            detail: image detail sent with each image ("low", "high", "auto"), if any.
            price_per_mtok: (input, output) USD per million tokens, for a cost estimate.
            check: verify the backend (key, reachability) now, not at step 40.
            images: the format and size the observations' images are sent in.
        """
        self.backend = backend
        self.prompt = prompt or PromptConfig()
        self.max_requeries = max_requeries
        self.detail = detail
        self.price_per_mtok = price_per_mtok
        self.images = images
        self.name = f"vlm:{backend.model}{design_suffix(self.prompt.design)}"
        # Rendered once now so a broken template fails before the first step, then for
        # each new camera (depth range, field of view) the observations come from.
        self._system: dict[tuple[tuple[float, float], float, Instruments] | None, str] = {
            None: render_system(self.prompt)
        }
        self._history: deque[EncodedObservation] = deque(maxlen=max(self.prompt.history, 0) or None)
        if self.prompt.history == 0:
            self._history = deque(maxlen=0)
        # The map of `--map-image`: built from the observations, moved by the actions
        # executed (or, when an observation does not say, the one this pilot chose).
        self.map = CaveMap() if self.prompt.map_image else None
        # The arrows and waypoint designs: what draws the choices and flies them.
        prompt = self.prompt
        self.helm = None
        if prompt.design != "direct":
            self.helm = Helm(prompt.design, prompt.rules, prompt.space, prompt.replan_every)
        self._last: Action | None = None
        if check:
            backend.check()

    def reset(self) -> None:
        self._history.clear()
        self._last = None
        if self.helm is not None:
            self.helm.reset()
        if self.map is not None:
            self.map.reset()

    def _cost(self, prompt_tokens: int, completion_tokens: int) -> float | None:
        if self.price_per_mtok is None:
            return None
        price_in, price_out = self.price_per_mtok
        return (prompt_tokens * price_in + completion_tokens * price_out) / 1e6

    def _system_for(self, observation: Observation) -> str:
        instruments = Instruments.of(observation)
        key = (observation.depth_range, observation.hfov_deg, instruments)
        if key not in self._system:
            self._system[key] = render_system(self.prompt, *key)
        return self._system[key]

    def decide(self, observation: Observation) -> Decision:
        if self.map is not None:  # at every step: a waypoint's planner asks at some only
            self.map.update(observation, executed_since(observation, self._last))
        if self.helm is not None:
            return self._decide_designed(observation, self.helm)
        current = self._encoded(observation, observation.rgb)
        messages = self._messages(observation, current)
        space = self.prompt.space
        parsed, exchanges, completion = self._ask(messages, lambda text: parse_reply(text, space))
        self._last = parsed.action
        self._history.append(replace(current, action=parsed.action_text, sonar_url=None))
        return Decision(
            action=parsed.action,
            action_text=parsed.action_text,
            justification=parsed.justification,
            raw=completion.text,
            usage=self._usage(exchanges),
            exchanges=self._records(exchanges),
        )

    def _encoded(self, observation: Observation, colour: np.ndarray) -> EncodedObservation:
        """``observation`` as a request carries it, ``colour`` as its colour image."""
        sonar = observation.sonar
        return EncodedObservation(
            data_url(colour, self.images),
            data_url(observation.depth_png, self.images) if observation.has_depth else None,
            observation.d_top,
            observation.d_bottom,
            sonar_url=None if sonar is None else data_url(sonar.fan, PNG),
        )

    def _decide_designed(self, observation: Observation, helm: Helm) -> Decision:
        """A step of the arrows or waypoint design: the planner's toward a waypoint while
        it flies one, else the model's choice among the candidates drawn on the image."""
        planned = helm.planned(observation)
        if planned is not None:
            self._last = planned.action
            return planned
        candidates, drawn = helm.offer(observation)
        remember_drawing(observation.rgb, drawn)
        current = self._encoded(observation, drawn)
        offered = "Numbers offered: " + "; ".join(c.words() for c in candidates) + "."
        if helm.stopped:
            offered = f"The planner stopped: {helm.stopped}. {offered}"
        messages = self._messages(observation, current, offered)

        def read(text: str) -> Choice:
            key, justification = final_answer(text)
            choice = read_choice(
                str(key).strip(), justification, helm.design, candidates, self.prompt.space
            )
            helm.check(observation, choice)
            return choice

        choice, exchanges, completion = self._ask(messages, read)
        flown = helm.fly(observation, choice, candidates)
        self._last = flown.action
        self._history.append(
            replace(current, action=f"{choice.text} ({flown.action_text})", sonar_url=None)
        )
        return replace(
            flown,
            justification=choice.justification,
            raw=completion.text,
            usage=self._usage(exchanges),
            exchanges=self._records(exchanges),
        )

    def _ask(
        self, messages: list[Message], parse: Callable[[str], Parsed]
    ) -> tuple[Parsed, list[Exchange], Completion]:
        """Ask the model until ``parse`` accepts a reply, each rejected reply sent back
        with the reason, at most `max_requeries` times.

        Raises:
            PilotFailure: the backend gave up, or no reply was usable.
        """
        schema = STRUCTURED_SCHEMA if self.prompt.structured else None
        exchanges: list[Exchange] = []
        reason = ""
        for _ in range(self.max_requeries + 1):
            try:
                completion = self.backend.complete(messages, schema)
            except BackendError as exc:
                exchanges.append(Exchange.failed(messages, exc))
                cause = "auth" if isinstance(exc, BackendAuthError) else "backend"
                raise self._failure(f"backend failed: {exc}", exchanges, cause) from None
            try:
                parsed = parse(completion.text)
            except ActionError as exc:
                reason = str(exc)
                exchanges.append(Exchange(list(messages), completion, reason))
                messages = messages + [
                    {"role": "assistant", "content": completion.text},
                    {"role": "user", "content": render_repair(self.prompt, reason)},
                ]
                continue
            exchanges.append(Exchange(list(messages), completion))
            return parsed, exchanges, completion
        raise self._failure(
            f"no usable reply after {self.max_requeries + 1} attempts; last problem: {reason}",
            exchanges,
        )

    def _messages(
        self, observation: Observation, current: EncodedObservation, offered: str | None = None
    ) -> list[dict[str, Any]]:
        """The request for this step: system prompt, history, map and current images, and
        the choices offered (a design's)."""
        if self._history and observation.previous_action is not None and self.helm is None:
            # The action actually executed (a shield may have replaced the proposal).
            last = self._history[-1]
            self._history[-1] = replace(last, action=format_action(observation.previous_action))
        map_view = None
        if self.map is not None:
            span = self.prompt.map_span_m
            map_view = (self.map.describe(), png_data_url(self.map.top_down(span_m=span)))
        system = self._system_for(observation)
        energy = observation.energy_left_wh if self.prompt.energy else None
        history = list(self._history)
        return build_messages(system, current, history, self.detail, map_view, energy, offered)

    def _records(self, exchanges: list[Exchange]) -> tuple[dict[str, Any], ...]:
        return tuple(e.to_record(self.backend.model) for e in exchanges)

    def _failure(
        self, message: str, exchanges: list[Exchange], cause: str = "reply"
    ) -> PilotFailure:
        """The episode-ending failure, carrying the failed step's records and cost."""
        usage = self._usage(exchanges) if exchanges else None
        return PilotFailure(message, self._records(exchanges), usage, cause=cause)

    def _usage(self, exchanges: list[Exchange]) -> Usage:
        """What the step's requests cost; each request after the first was a re-query."""
        prompt_tokens = sum(e.completion.prompt_tokens for e in exchanges)
        completion_tokens = sum(e.completion.completion_tokens for e in exchanges)
        return Usage(
            prompt_tokens=prompt_tokens,
            completion_tokens=completion_tokens,
            latency_s=sum(e.completion.latency_s for e in exchanges),
            model_s=_sum_known([e.completion.model_s for e in exchanges]),
            requeries=max(len(exchanges) - 1, 0),
            transport_retries=sum(e.completion.retries for e in exchanges),
            cached=all(e.completion.cached for e in exchanges),
            cost_usd=self._cost(prompt_tokens, completion_tokens),
        )


def _sum_known(values: list[float | None]) -> float | None:
    """The sum, or None where any part was not measured (a cached or failed request)."""
    return None if any(v is None for v in values) else sum(values)  # type: ignore[arg-type]
