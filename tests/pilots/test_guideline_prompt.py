"""The prompt speaks of the cave line only where the cave has one."""

from __future__ import annotations

from dataclasses import replace

import pytest

from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.backends import OpenAIBackend, OpenAIConfig
from cavenav.pilots.prompt import Instruments, PromptConfig, render_system
from cavenav.pilots.vlm import VLMPilot
from cavenav.world.scenarios import load_scenario
from tests.conftest import synthetic_observation
from tests.vlm_server import FakeVLM


@pytest.mark.parametrize("colour", ["white", "yellow"])
def test_the_prompt_says_a_guideline_may_show_and_its_arrows_point_out(colour: str) -> None:
    text = render_system(PromptConfig(), instruments=Instruments(guideline=colour))
    section = text[text.index("# The cave line") :]
    assert f"thin {colour} guideline" in section
    assert "arrows" in section and "point toward the exit" in section
    assert "{" not in section  # every field filled


def test_without_a_line_the_prompt_never_mentions_one() -> None:
    for design in ("direct", "arrows", "waypoint"):
        text = render_system(PromptConfig(design=design), instruments=Instruments())
        assert "guideline" not in text.lower(), design
    assert render_system(PromptConfig()) == render_system(
        PromptConfig(), instruments=Instruments.of(synthetic_observation(5.0))
    )


def test_the_instruments_read_the_line_from_the_observation() -> None:
    seen = replace(synthetic_observation(5.0), guideline="yellow")
    assert Instruments.of(seen).guideline == "yellow"
    assert Instruments.of(synthetic_observation(5.0)).guideline is None


@pytest.mark.parametrize("guideline", [True, False])
def test_the_vlm_pilot_is_told_of_the_line_in_a_cave_that_has_one(guideline: bool) -> None:
    with FakeVLM() as server:
        config = OpenAIConfig(model="fake-vlm", base_url=server.base_url, timeout_s=5.0)
        episode = EpisodeConfig(max_steps=1, plots=False, save_frames=False, guideline=guideline)
        run_episode(load_scenario("S4"), VLMPilot(OpenAIBackend(config)), episode)
        system = server.requests[0]["messages"][0]["content"]
    assert ("# The cave line" in system) is guideline
    assert ("thin white guideline" in system) is guideline
