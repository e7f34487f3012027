"""The pilot designs: numbered arrows and waypoints drawn on the image, read from replies,
and flown by the geometric pilot's standoff rules (`cavenav.pilots.designs`)."""

from __future__ import annotations

import base64
import io
import json
import math

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import ActionError, ConfigError, PilotFailure
from cavenav.core.types import DEFAULT_RULES
from cavenav.motion.actions import DEFAULT_SPACE
from cavenav.pilots.backends import Completion
from cavenav.pilots.designs import (
    Candidate,
    Choice,
    draw_candidates,
    offer_candidates,
    read_choice,
    waypoint_goal,
)
from cavenav.pilots.geometric import FreeView, GeometricPilot
from cavenav.pilots.prompt import PromptConfig, render_system
from cavenav.pilots.vlm import VLMPilot
from tests.conftest import synthetic_observation

BEARINGS = np.arange(-25.0, 25.01, 2.5)
ELEVATIONS = np.arange(-18.0, 18.01, 3.0)


def view_open_between(low: float, high: float, free_m: float = 12.0) -> FreeView:
    """A view where the body fits for ``free_m`` at bearings ``low``-``high``, 1 m elsewhere."""
    free = np.full((len(BEARINGS), len(ELEVATIONS)), 1.0)
    free[(low <= BEARINGS) & (high >= BEARINGS)] = free_m
    return FreeView(BEARINGS, ELEVATIONS, free, False)


class Scripted:
    """A backend that answers with the replies it was given, in order."""

    model = "script"

    def __init__(self, *replies: str):
        self.replies = list(replies)
        self.sent: list[list[dict]] = []

    def check(self) -> None: ...

    def complete(self, messages: list[dict], json_schema: dict | None = None) -> Completion:
        self.sent.append(messages)
        return Completion(self.replies.pop(0), prompt_tokens=100, completion_tokens=20)


def answer(key: str) -> str:
    return f"(a) open ahead. (c) I choose {key}.\n" + json.dumps({key: "open water that way"})


def test_arrows_point_only_where_the_body_fits_numbered_left_to_right_between_two_turns() -> None:
    candidates = offer_candidates(view_open_between(-10.0, 20.0), 53.13, (480, 640), 2.5)
    first, *ahead, last = candidates
    assert [c.number for c in candidates] == list(range(1, len(candidates) + 1))
    assert first.turn and first.bearing_deg == 45 and last.turn and last.bearing_deg == -45
    assert ahead and all(-10.0 <= c.bearing_deg <= 20.0 and c.free_m == 12.0 for c in ahead)
    bearings = [c.bearing_deg for c in ahead]
    assert bearings == sorted(bearings, reverse=True)  # left to right on the image
    assert all(a - b >= 7.5 for a, b in zip(bearings, bearings[1:], strict=False))
    assert [c.x for c in ahead] == sorted(c.x for c in ahead)
    # Nothing the body fits through: only the turns are offered.
    walled = offer_candidates(view_open_between(0.0, 0.0, free_m=2.0), 53.13, (480, 640), 2.5)
    assert [c.turn for c in walled] == [True, True]


def test_the_drawn_numbers_stay_legible_after_jpeg_and_a_quarter_of_the_pixels() -> None:
    rgb = np.full((480, 640, 3), 30, np.uint8)  # dark water
    candidates = offer_candidates(view_open_between(-20.0, 20.0), 53.13, (480, 640), 2.5)
    drawn = draw_candidates(rgb, candidates)
    assert not np.shares_memory(drawn, rgb) and (rgb == 30).all()  # the frame is untouched
    buffer = io.BytesIO()
    Image.fromarray(drawn).resize((320, 240), Image.Resampling.BOX).save(buffer, "JPEG", quality=50)
    seen = np.asarray(Image.open(buffer).convert("L"), np.float32)
    for c in candidates:
        x, y = c.x * 320, c.y * 240
        if c.turn:  # the disc sits inward of the edge, above the arrow
            x += (1 if c.x < 0.5 else -1) * 2 * 17 / 2
            y -= 2 * 17 / 2
        disc = seen[int(y) - 4 : int(y) + 5, int(x) - 7 : int(x) + 8]
        assert disc.max() > 200 and disc.min() < 90, c  # white disc, dark digit
    assert seen[5:40, 200:260].max() < 60  # and the water around stays dark


def test_a_reply_chooses_an_offered_number_or_a_point_and_anything_else_is_refused() -> None:
    candidates = offer_candidates(view_open_between(-10.0, 10.0), 53.13, (480, 640), 2.5)
    numbers = [c.number for c in candidates]
    chosen = read_choice("arrow 2, ascend 0.3 m", "why", "arrows", candidates, DEFAULT_SPACE)
    assert chosen.candidate == candidates[1] and chosen.up_m == 0.3
    assert read_choice("3", "", "arrows", candidates, DEFAULT_SPACE).up_m is None
    written_by_models = (
        "Arrow 3",
        "#3",
        "3.",
        "3 - descend 0.2 m",
        "3 = straight ahead, 6.0 m free",
    )
    for written in written_by_models:
        assert read_choice(written, "", "arrows", candidates, DEFAULT_SPACE).candidate.number == 3
    point = read_choice("point 0.62, 0.41", "", "waypoint", candidates, DEFAULT_SPACE)
    assert point.point == (0.62, 0.41) and point.candidate is None
    for written in ("(0.5, 0.5)", "[0.5, 0.5]", "x: 0.5, y: 0.5", "x=0.5, y=0.5"):
        assert read_choice(written, "", "waypoint", candidates, DEFAULT_SPACE).point == (0.5, 0.5)
    assert read_choice("point 2", "", "waypoint", candidates, DEFAULT_SPACE).candidate.number == 2
    refused = {
        ("arrows", "9"): f"number 9 was not offered: choose one of {', '.join(map(str, numbers))}",
        ("arrows", "2, forward 1 m"): "only ascend or descend may follow the number",
        ("arrows", "2, ascend 7 m"): "vertical 7 m is not admissible",
        ("arrows", "forward 1 m"): "is not a choice: answer with the number of an arrow",
        ("arrows", "0.5, 0.5"): "is not a choice",  # a point, where a number is asked
        ("waypoint", "point 1.4, 0.5"): "lies outside the image",
        ("waypoint", "point -0.1, 0.5"): "lies outside the image",
        ("waypoint", "2, descend 0.2 m"): "give the number alone",
        ("waypoint", "go left"): "is not a choice",
    }
    for (design, key), says in refused.items():
        with pytest.raises(ActionError) as caught:
            read_choice(key, "", design, candidates, DEFAULT_SPACE)  # type: ignore[arg-type]
        assert says in str(caught.value), (key, str(caught.value))


def test_a_waypoint_is_short_of_the_rock_by_the_standoff_and_one_on_near_rock_is_refused() -> None:
    far = synthetic_observation(10.0)
    view = GeometricPilot().survey(far)
    goal = waypoint_goal(far, view, Choice("point 0.5, 0.5", "", point=(0.5, 0.5)), DEFAULT_RULES)
    # A wall 10 m ahead of the camera, which sits 0.2 m ahead of the centre; 2 m short.
    assert goal[0] == pytest.approx(10.2 - DEFAULT_RULES.standoff_m, abs=0.15)
    assert abs(goal[1]) < 0.05 and abs(goal[2]) < 0.05
    # A corner of the image: the surface there is farther along a slanted ray.
    corner = waypoint_goal(far, view, Choice("p", "", point=(0.05, 0.5)), DEFAULT_RULES)
    assert corner[1] > 3.0  # far to the left
    near = synthetic_observation(2.2)
    near_view = GeometricPilot().survey(near)
    with pytest.raises(ActionError, match="within the 2 m standoff"):
        waypoint_goal(near, near_view, Choice("p", "", point=(0.5, 0.5)), DEFAULT_RULES)


def arrows_pilot(*replies: str, design: str = "arrows", **prompt: object) -> VLMPilot:
    config = PromptConfig(design=design, **prompt)  # type: ignore[arg-type]
    return VLMPilot(Scripted(*replies), config, check=False)


def test_an_arrow_not_offered_is_asked_again_with_the_reason_then_flown() -> None:
    pilot = arrows_pilot(answer("99"), answer("3"))
    decision = pilot.decide(synthetic_observation(12.0))
    first, second = decision.exchanges
    assert "number 99 was not offered" in first["rejected"] and second["rejected"] is None
    repair = second["messages"][-1]["content"]
    assert "number 99 was not offered" in repair
    assert "the number of one arrow offered" in repair and "strafe" not in repair
    assert decision.usage is not None and decision.usage.requeries == 1
    chosen = decision.extra["choice"]
    assert chosen == {"text": "3", "number": 3}
    arrow = next(c for c in decision.extra["candidates"] if c["number"] == 3)
    # The arrow's direction, sized by the standoff rules: far water, but into a bend
    # (15 degrees) whose inner wall is out of view, half a metre.
    assert decision.action.forward == 0.5 and decision.extra["design"] == "arrows"
    assert abs(decision.action.yaw_deg - arrow["bearing_deg"]) <= 5.0
    assert decision.justification == "open water that way" and not decision.extra["planned"]


def test_a_request_shows_the_drawn_image_and_lists_the_numbers_offered() -> None:
    backend = Scripted(answer("2"))
    pilot = VLMPilot(backend, PromptConfig(design="arrows"), check=False)
    observation = synthetic_observation(12.0)
    decision = pilot.decide(observation)
    system, user = backend.sent[0]
    assert "# The numbered arrows" in system["content"] and "# The action" not in system["content"]
    texts = [p["text"] for p in user["content"] if p["type"] == "text"]
    offered = texts[-2]
    assert offered.startswith("Numbers offered: 1 = turn left 45 degrees in place; 2 = ")
    assert len(decision.extra["candidates"]) == offered.count(" = ")
    images = [p["image_url"]["url"] for p in user["content"] if p["type"] == "image_url"]
    sent = np.asarray(Image.open(io.BytesIO(base64.b64decode(images[0].split(",")[1]))))
    assert sent.shape == observation.rgb.shape and sent.max() == 255  # drawn on a black frame


def test_a_persistently_wrong_design_ends_as_a_pilot_failure() -> None:
    pilot = arrows_pilot(*[answer("42")] * 4)
    with pytest.raises(PilotFailure, match="number 42 was not offered") as caught:
        pilot.decide(synthetic_observation(12.0))
    assert len(caught.value.exchanges) == 4


def test_the_planner_flies_to_the_waypoint_without_calls_and_asks_again_when_there() -> None:
    backend = Scripted(answer("point 0.5, 0.5"), answer("point 0.5, 0.5"))
    pilot = arrows_pilot(design="waypoint", replan_every=3)
    pilot.backend = backend
    decisions = [pilot.decide(synthetic_observation(12.0)) for _ in range(4)]
    assert [len(d.exchanges) for d in decisions] == [1, 0, 0, 1]  # three steps, then asked
    assert [d.extra["planned"] for d in decisions] == [False, True, True, False]
    assert all(d.usage is None for d in decisions[1:3])
    assert decisions[0].extra["goal"][0] == pytest.approx(12.2 - 2.0, abs=0.2)
    assert "The planner stopped: 3 steps flown toward the waypoint" in json.dumps(
        backend.sent[1][1]["content"]
    )


def test_a_waypoint_on_near_rock_is_asked_again() -> None:
    pilot = arrows_pilot(answer("point 0.5, 0.5"), answer("1"), design="waypoint")
    decision = pilot.decide(synthetic_observation(2.3))
    assert "within the 2 m standoff" in decision.exchanges[0]["rejected"]
    assert decision.action.yaw_deg == 45 and not decision.action.forward  # the turn chosen


def test_designs_render_their_own_closing_sections_and_direct_stays_the_papers() -> None:
    direct = render_system(PromptConfig())
    assert "# The action" in direct and "# Your reply" in direct
    for design, heading in (("arrows", "# The numbered arrows"), ("waypoint", "# Your waypoint")):
        text = render_system(PromptConfig(design=design, replan_every=5))  # type: ignore[arg-type]
        assert heading in text and "# The action" not in text
        assert text.startswith(direct[: direct.index("# The action")])
    assert "after 5 steps" in render_system(PromptConfig(design="waypoint", replan_every=5))


@pytest.mark.parametrize(
    ("settings", "says"),
    [
        ({"design": "oracle"}, "unknown --design 'oracle'"),
        ({"replan_every": 0}, "--replan-every 0"),
    ],
)
def test_an_unknown_design_or_no_planner_steps_is_refused(settings: dict, says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        PromptConfig(**settings)


def test_candidates_and_choices_are_plain_records() -> None:
    c = Candidate(3, 12.5, -3.0, 7.25, 0.31, 0.52)
    assert json.loads(json.dumps(c.to_dict())) == c.to_dict()
    assert c.words() == "3 = 12 degrees left, 3 degrees down, 7.2 m free"
    assert Candidate(1, 45.0, 0.0, 0.0, 0.03, 0.5).words() == "1 = turn left 45 degrees in place"
    assert math.isclose(Choice("x", "", point=(0.5, 0.25)).to_dict()["point"][1], 0.25)


def test_the_pilots_map_moves_with_every_step_the_planner_flies_without_a_call() -> None:
    pilot = arrows_pilot(answer("point 0.5, 0.5"), design="waypoint", map_image=True)
    moves = [pilot.decide(synthetic_observation(12.0)).action for _ in range(4)]
    assert pilot.map is not None and all(m.yaw_deg == 0 for m in moves[:3])
    # The map has moved by the three moves flown before the fourth observation.
    assert pilot.map.position[0] == pytest.approx(sum(m.forward for m in moves[:3]), abs=1e-6)


def test_after_a_look_aside_the_turn_back_is_flown_without_asking_the_model() -> None:
    pilot = arrows_pilot(answer("3"))
    observation = synthetic_observation(12.0)
    pilot.decide(observation)
    # The helmsman turned to look at a side it would shift to: the turn back is its own.
    pilot.helm.helmsman.state = pilot.helm.helmsman.state.looking(-45.0, np.zeros(3))
    turned = pilot.decide(synthetic_observation(12.0))
    assert turned.action.yaw_deg == -45.0 and not turned.exchanges and turned.extra["planned"]


def test_structured_mode_asks_for_the_designs_answer() -> None:
    arrows = render_system(PromptConfig(design="arrows", structured=True))
    assert "the arrow's number, and its short justification" in arrows
    assert "the action string" in render_system(PromptConfig(structured=True))
