"""The HTML report, read as a user reads it: pages that open from disk and show the record.

Real run folders are flown once per module in the 20 m test corridor (a scripted pilot
that turns into a wall, the same under the shield, and the VLM pilot against the local
test server); sweep folders are assembled from them as `cavenav eval` lays them out.
"""

from __future__ import annotations

import json
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import lxml.html
import pytest

from cavenav.core.errors import CavenavError
from cavenav.core.types import Decision, Observation, Pose
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.report import write_report
from cavenav.evaluation.sweep import SweepConfig, plan, read_rows
from cavenav.motion.actions import parse_action
from cavenav.pilots.backends import OpenAIBackend, OpenAIConfig
from cavenav.pilots.vlm import VLMPilot
from cavenav.world.scenarios import ExitPortal, Scenario
from tests.conftest import box_room
from tests.vlm_server import FakeVLM

# Turn to face the side wall 2 m away, then drive into it: the collision is step 2.
INTO_THE_WALL = ("turn left 90 deg", "forward 1 m", "forward 1 m", "forward 1 m")
INJECTED = "<script>alert('owned')</script> I see <b>rock</b>."


class ScriptedPilot:
    """Flies a fixed list of actions, the last one repeated."""

    name = "scripted"

    def __init__(self, actions: tuple[str, ...]):
        self.actions = actions
        self._k = 0

    def reset(self) -> None:
        self._k = 0

    def decide(self, observation: Observation) -> Decision:
        text = self.actions[min(self._k, len(self.actions) - 1)]
        self._k += 1
        return Decision(parse_action(text), text, f"scripted move {self._k}")


def corridor() -> Scenario:
    """The 20 m, 4 m square test corridor of conftest, heading -y from y = 8."""
    return Scenario(
        name="room",
        mesh=box_room(),
        start=Pose(0.0, 8.0, 0.0, 0.0),
        exits=(ExitPortal((0.0, -6.0, 0.0), (0.0, -1.0, 0.0), 3.0),),
        description="test corridor",
    )


def fly_vlm(run_dir: Path) -> None:
    """Three steps of the VLM pilot; the first reply is unusable, every reply injects HTML."""
    with FakeVLM() as server:
        server.faults.append("garbage")
        answer = server.answer
        server.answer = lambda body: f"{INJECTED}\n{answer(body)}"  # type: ignore[method-assign]
        config = OpenAIConfig(
            model="fake-vlm", base_url=server.base_url, timeout_s=2.0, backoff_s=0.01
        )
        pilot = VLMPilot(OpenAIBackend(config), price_per_mtok=(0.5, 1.5))
        episode = EpisodeConfig(max_steps=3, save_frames=False, plots=False)
        run_episode(corridor(), pilot, episode, run_dir)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("runs")
    pilot = ScriptedPilot(INTO_THE_WALL)
    run_episode(corridor(), pilot, EpisodeConfig(max_steps=6), root / "crash")
    shielded = EpisodeConfig(max_steps=4, shield=True, save_frames=False, plots=False)
    run_episode(corridor(), pilot, shielded, root / "shielded")
    fly_vlm(root / "vlm")
    return {name: root / name for name in ("crash", "shielded", "vlm")}


def make_sweep(root: Path, episodes: dict[str, Path], frames: str = "all") -> Path:
    """A sweep folder as `cavenav eval` leaves it: sweep.json, the run folders under
    episodes/ (named as the grid names them), results.csv and aggregate.json."""
    config = SweepConfig(("room",), tuple(range(len(episodes))), frames=frames)
    root.mkdir(parents=True)
    (root / "sweep.json").write_text(json.dumps(config.to_dict()))
    for job, (episode, run) in zip(plan(config), episodes.items(), strict=True):
        assert job.episode == episode
        shutil.copytree(run, root / "episodes" / episode)
    read_rows(root)  # writes results.csv and aggregate.json
    return root


class Page(HTMLParser):
    """What a reader of a page sees: its text, its links and images, its elements."""

    def __init__(self, path: Path):
        super().__init__()
        self.path = path
        self.html = path.read_text(encoding="utf-8")
        self.text_parts: list[str] = []
        self.links: list[tuple[str, str]] = []  # (tag, url)
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.feed(self.html)

    def table(self, index: int) -> list[dict[str, lxml.html.HtmlElement]]:
        """The body rows of the page's ``index``-th table: header -> cell, as read."""
        table = lxml.html.fromstring(self.html).xpath("//table")[index]
        headers = [" ".join(th.text_content().split()) for th in table.xpath(".//thead//th")]
        return [
            dict(zip(headers, row.xpath("./td"), strict=True)) for row in table.xpath("./tbody/tr")
        ]

    def nav(self, label: str) -> Path | None:
        """The page a link whose text starts with ``label`` leads to, None without one."""
        for link in lxml.html.fromstring(self.html).xpath("//nav//a"):
            if link.text_content().strip().startswith(label):
                return (self.path.parent / unquote(link.get("href"))).resolve()
        return None

    def facts(self, values: bool = False) -> list[str]:
        """The labels (or, with ``values``, the values) of the page's first fact list."""
        (facts,) = lxml.html.fromstring(self.html).xpath("(//dl)[1]")
        return [text(item) for item in facts.xpath("./dd" if values else "./dt")]

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))
        for name, value in attrs:
            if name in ("href", "src") and value is not None:
                self.links.append((tag, value))

    def handle_data(self, data: str) -> None:
        self.text_parts.append(data)

    @property
    def text(self) -> str:
        return " ".join(" ".join(self.text_parts).split())

    def local_targets(self) -> list[Path]:
        """The files the page's relative links and images point to (anchors dropped)."""
        targets = []
        for _, url in self.links:
            assert "://" not in url, f"{self.path.name} reaches out to {url}"
            if not url.startswith("#"):
                targets.append(self.path.parent / unquote(url.split("#")[0]))
        return targets


def text(cell: lxml.html.HtmlElement) -> str:
    return " ".join(cell.text_content().split())


def badge(cell: lxml.html.HtmlElement) -> tuple[str, str]:
    """The outcome badge in ``cell``: its word and its colour class (ok, bad, warn, other)."""
    (span,) = cell.find_class("outcome")
    (colour,) = set(span.get("class").split()) - {"outcome"}
    return text(span), colour


@pytest.fixture(scope="module")
def sweep(runs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    episodes = {"room-seed0000": runs["crash"], "room-seed0001": runs["shielded"]}
    folder = make_sweep(tmp_path_factory.mktemp("sweep") / "sweep", episodes)
    write_report(folder)
    return folder


def test_the_index_links_every_episode_to_a_page_that_exists(sweep: Path) -> None:
    index = Page(sweep / "report" / "index.html")
    pages = {url for tag, url in index.links if tag == "a" and url.startswith("episodes/")}
    assert pages == {"episodes/room-seed0000.html", "episodes/room-seed0001.html"}
    for target in index.local_targets():
        assert target.exists(), f"index.html links to a missing {target}"
    # the crashed episode's topdown plot is its thumbnail, loaded lazily
    thumbs = [a for tag, a in index.tags if tag == "img"]
    assert [t["src"] for t in thumbs] == ["../episodes/room-seed0000/topdown.png"]
    assert thumbs[0]["loading"] == "lazy"


def test_every_link_and_image_of_every_episode_page_resolves(sweep: Path) -> None:
    for page_path in sorted((sweep / "report" / "episodes").glob("*.html")):
        page = Page(page_path)
        assert ("a", "../index.html") in page.links
        for target in page.local_targets():
            assert target.exists(), f"{page_path.name} links to a missing {target}"


def test_the_index_shows_the_aggregate_and_hides_columns_empty_for_the_whole_sweep(
    sweep: Path,
) -> None:
    index = Page(sweep / "report" / "index.html")
    (room, everything) = index.table(0)  # the scenario's row, then all scenarios
    assert text(room["success [95% CI]"]) == "0% [0-66]"  # 0 of 2, its 95% Wilson interval
    assert text(room["outcomes"]) == "collision 1 · oscillating 1"  # shielded, no headway
    assert text(room["min clearance: min / mean"]).endswith(" m")
    assert text(everything["scenario"]) == "all"
    # No model flew: no token or cost columns, in either table.
    for headers in (set(index.table(0)[0]), set(index.table(1)[0])):
        assert not {"prompt tokens", "completion tokens", "tokens in / out", "cost"} & headers


def test_outcomes_are_coloured_collision_red_others_amber(sweep: Path) -> None:
    index = Page(sweep / "report" / "index.html")
    shown = {text(row["episode"]): badge(row["outcome"]) for row in index.table(1)}
    assert shown == {
        "room-seed0000": ("collision", "bad"),
        "room-seed0001": ("oscillating", "warn"),
    }
    crashed = Page(sweep / "report" / "episodes" / "room-seed0000.html")
    (heading,) = lxml.html.fromstring(crashed.html).xpath("//h1")
    assert badge(heading) == ("collision", "bad")


def test_an_episode_page_shows_the_reasoning_and_why_a_reply_was_rejected(
    runs: dict[str, Path],
) -> None:
    page = Page(write_report(runs["vlm"]))
    exchanges = [json.loads(line) for line in (runs["vlm"] / "exchanges.jsonl").open()]
    rejected = next(e for e in exchanges if e["rejected"])
    assert "re-query 1" in page.text
    assert f"rejected: {rejected['rejected']}" in page.text
    for exchange in exchanges:  # every attempt's raw reply, reasoning included
        assert " ".join(exchange["reply"].split()) in page.text
    # one folded block for the system prompt, then one per request
    assert sum(1 for tag, _ in page.tags if tag == "details") == 1 + len(exchanges)
    assert "open all reasoning" in page.text  # one control opens every request's reply
    assert page.html.count('<details class="reasoning">') == len(exchanges)


def test_model_text_is_escaped_never_run(runs: dict[str, Path]) -> None:
    page = Page(write_report(runs["vlm"]))
    assert INJECTED in page.text  # shown to the reader as the model wrote it
    assert not any(tag == "b" for tag, _ in page.tags)  # never markup
    assert [tag for tag, _ in page.tags].count("script") == 1  # the page's own control only


def test_a_run_without_frames_shows_the_images_the_model_was_sent(
    runs: dict[str, Path],
) -> None:
    page = Page(write_report(runs["vlm"]))
    images = [attrs for tag, attrs in page.tags if tag == "img"]
    assert len(images) == 2 * 3  # colour and depth for each of the 3 steps
    assert all(i["src"].startswith("images/") and i["loading"] == "lazy" for i in images)
    assert all((runs["vlm"] / i["src"]).is_file() for i in images)
    # The images shown are the ones steps.jsonl names: those the step's first request
    # introduced as the current observation, not the earlier ones it also carried.
    steps = [json.loads(line) for line in (runs["vlm"] / "steps.jsonl").open()]
    exchanges = [json.loads(line) for line in (runs["vlm"] / "exchanges.jsonl").open()]
    for step in steps:
        first = next(e for e in exchanges if e["step"] == step["step"])
        parts = first["messages"][1]["content"]
        k = next(i for i, p in enumerate(parts) if p.get("text", "").startswith("Current obs"))
        current = {"rgb": parts[k + 1]["file"], "depth_png": parts[k + 2]["file"]}
        assert step["model_images"] == current
    shown = [unquote(i["src"]) for i in images]
    assert shown == [s["model_images"][key] for s in steps for key in ("rgb", "depth_png")]


def test_a_run_written_before_model_images_shows_the_images_its_requests_carried(
    runs: dict[str, Path], tmp_path: Path
) -> None:
    # A VLM run folder as written before steps.jsonl named model_images: no frames, the
    # images only in exchanges.jsonl, the current ones after the "Current observation" text.
    old = tmp_path / "old-run"
    shutil.copytree(runs["vlm"], old)
    steps = [json.loads(line) for line in (old / "steps.jsonl").open()]
    current = [step.pop("model_images") for step in steps]
    assert all(not step.get("frames") for step in steps)
    (old / "steps.jsonl").write_text("".join(json.dumps(s) + "\n" for s in steps))
    page = Page(write_report(old))
    shown = [unquote(attrs["src"]) for tag, attrs in page.tags if tag == "img"]
    assert shown == [c[key] for c in current for key in ("rgb", "depth_png")]
    assert page.text.count("frames not saved; images from the model request") == len(steps)


def test_the_shield_intervention_and_the_collision_step_are_shown(sweep: Path) -> None:
    crashed = Page(sweep / "report" / "episodes" / "room-seed0000.html")
    steps = [json.loads(line) for line in (sweep / "episodes/room-seed0000/steps.jsonl").open()]
    hit = next(s["step"] for s in steps if s["collision"])
    assert hit == 2
    sections = {a["id"]: a["class"] for tag, a in crashed.tags if tag == "section"}
    assert "collision" in sections[f"step-{hit}"].split()
    assert not any("collision" in c.split() for i, c in sections.items() if i != f"step-{hit}")
    assert "Collision during this move" in crashed.text

    shielded = Page(sweep / "report" / "episodes" / "room-seed0001.html")
    records = [json.loads(line) for line in (sweep / "episodes/room-seed0001/steps.jsonl").open()]
    shield = next(s["shield"] for s in records if s.get("shield"))
    assert f"Shield: {shield['proposed']} → {shield['replacement']}" in shielded.text
    assert shield["reason"] in shielded.text


def test_a_sweep_flown_without_frames_says_no_frames_were_saved(
    runs: dict[str, Path], tmp_path: Path
) -> None:
    folder = make_sweep(tmp_path / "sweep", {"room-seed0000": runs["shielded"]}, frames="none")
    write_report(folder)
    page = Page(folder / "report" / "episodes" / "room-seed0000.html")
    steps = len((runs["shielded"] / "steps.jsonl").read_text().splitlines())
    assert page.text.count("no frames saved (--frames none)") == steps
    assert not any(tag == "img" for tag, _ in page.tags)


def test_an_interrupted_episode_gets_a_placeholder_saying_why(
    runs: dict[str, Path], tmp_path: Path
) -> None:
    folder = make_sweep(tmp_path / "sweep", {"room-seed0000": runs["crash"]})
    run = folder / "episodes" / "room-seed0000"
    summary = json.loads((run / "summary.json").read_text())
    (run / "summary.json").write_text(json.dumps({**summary, "status": "interrupted"}))
    (run / "topdown.png").unlink()
    (run / "side.png").unlink()
    index = Page(write_report(folder))
    assert "episode interrupted: no plot drawn" in index.text
    assert not any(tag == "img" for tag, _ in index.tags)


def test_a_run_folder_alone_gets_report_html_beside_its_files(runs: dict[str, Path]) -> None:
    page_path = write_report(runs["crash"])
    assert page_path == runs["crash"] / "report.html"
    page = Page(page_path)
    images = [a["src"] for tag, a in page.tags if tag == "img"]
    assert "topdown.png" in images and "frames/step_0000_rgb.png" in images
    assert all(target.exists() for target in page.local_targets())
    assert not any(url == "../index.html" for _, url in page.links)  # no sweep to go back to


def test_a_folder_that_is_neither_gives_one_clear_line(tmp_path: Path) -> None:
    with pytest.raises(CavenavError) as error:
        write_report(tmp_path)
    message = str(error.value)
    assert "\n" not in message
    assert str(tmp_path) in message and "sweep.json" in message and "summary.json" in message


def test_a_sweep_still_running_is_reported_from_its_episodes(
    runs: dict[str, Path], tmp_path: Path
) -> None:
    folder = make_sweep(tmp_path / "sweep", {"room-seed0000": runs["crash"]})
    (folder / "results.csv").unlink()
    (folder / "aggregate.json").unlink()
    index = Page(write_report(folder))
    assert "0% [0-79]" in index.text  # the aggregate, from the run folders themselves
    assert ("a", "episodes/room-seed0000.html") in index.links
    (row,) = index.table(1)
    assert badge(row["outcome"]) == ("collision", "bad")
    assert (folder / "report" / "episodes" / "room-seed0000.html").is_file()


CRASH = "RuntimeError: the sonar driver died"


@pytest.fixture(scope="module")
def mixed(runs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A sweep of four episodes: the VLM pilot (tokens and cost), a collision, one that
    crashed after reaching the exit (its summary otherwise reads success; no plots) and
    one never started (no run folder)."""
    episodes = {
        "room-seed0000": runs["vlm"],
        "room-seed0001": runs["crash"],
        "room-seed0002": runs["crash"],
        "room-seed0003": runs["crash"],
    }
    folder = make_sweep(tmp_path_factory.mktemp("mixed") / "sweep", episodes)
    crashed = folder / "episodes" / "room-seed0002"
    summary = json.loads((crashed / "summary.json").read_text())
    summary.update(status="crashed", error=CRASH, termination="exit", success=True)
    (crashed / "summary.json").write_text(json.dumps(summary))
    (crashed / "topdown.png").unlink()
    (crashed / "side.png").unlink()
    shutil.rmtree(folder / "episodes" / "room-seed0003")
    write_report(folder)
    return folder


def test_episode_pages_link_to_the_previous_and_next_episode_in_table_order(
    mixed: Path,
) -> None:
    index = Page(mixed / "report" / "index.html")
    order = [
        (index.path.parent / row["episode"].find("a").get("href")).resolve()
        for row in index.table(1)
    ]
    assert len(order) == 4
    forward, page = [order[0]], Page(order[0])
    assert page.nav("previous") is None  # the first has none
    while (after := page.nav("next")) is not None:
        forward.append(after)
        page = Page(after)
    assert forward == order  # missing run folder included, last one has no next
    backward = [order[-1]]
    while (before := Page(backward[-1]).nav("previous")) is not None:
        backward.append(before)
    assert backward == order[::-1]
    for path in order:
        assert Page(path).nav("←") == index.path.resolve()


def test_the_tokens_and_cost_of_a_model_are_shown_and_a_dash_for_pilots_without_one(
    mixed: Path,
) -> None:
    summary = json.loads((mixed / "episodes/room-seed0000/summary.json").read_text())
    usage = summary["usage"]
    assert usage["prompt_tokens"] > 0 and usage["cost_usd"] > 0
    index = Page(mixed / "report" / "index.html")
    vlm, collision = index.table(1)[:2]
    tokens_in, tokens_out = text(vlm["tokens in / out"]).replace(",", "").split(" / ")
    assert (int(tokens_in), int(tokens_out)) == (
        usage["prompt_tokens"],
        usage["completion_tokens"],
    )
    assert float(text(vlm["cost"]).lstrip("$")) == pytest.approx(usage["cost_usd"], abs=1e-4)
    assert text(collision["tokens in / out"]) == text(collision["cost"]) == "—"
    # The aggregate of the model's pilot totals them; the scripted pilot's shows none.
    groups = {(text(g["scenario"]), text(g["pilot"])): g for g in index.table(0)}
    model = groups[("all", summary["pilot"])]
    assert int(text(model["prompt tokens"]).replace(",", "")) == usage["prompt_tokens"]
    assert float(text(model["cost"]).lstrip("$")) == pytest.approx(usage["cost_usd"], abs=1e-4)
    assert text(groups[("all", "scripted")]["cost"]) == "—"
    page = Page(mixed / "report" / "episodes" / "room-seed0000.html")
    facts = dict(zip(page.facts(), page.facts(values=True), strict=True))
    tokens = [int(n) for n in re.findall(r"\d+", facts["tokens"].replace(",", ""))]
    assert tokens == [usage["prompt_tokens"], usage["completion_tokens"]]  # in, then out
    assert float(facts["cost"].lstrip("$")) == pytest.approx(usage["cost_usd"], abs=1e-4)


def test_a_crashed_episode_is_an_error_with_its_message_never_a_success(mixed: Path) -> None:
    index = Page(mixed / "report" / "index.html")
    row = index.table(1)[2]
    assert text(row["episode"]) == "room-seed0002"
    assert badge(row["outcome"]) == ("error", "other")
    assert text(row["error"]) == CRASH
    groups = {(text(g["scenario"]), text(g["pilot"])): g for g in index.table(0)}
    scripted = groups[("room", "scripted")]  # the collision and the crash: no success
    assert text(scripted["success [95% CI]"]).startswith("0% ")
    assert "success" not in text(scripted["outcomes"])
    assert "episode crashed before its plots were drawn" in index.text
    page = Page(mixed / "report" / "episodes" / "room-seed0002.html")
    (heading,) = lxml.html.fromstring(page.html).xpath("//h1")
    assert badge(heading) == ("error", "other")
    facts = dict(zip(page.facts(), page.facts(values=True), strict=True))
    assert (facts["outcome"], facts["status"]) == ("error", "crashed")


def test_an_episode_without_a_run_folder_gets_a_page_saying_it_will_be_flown_again(
    mixed: Path,
) -> None:
    index = Page(mixed / "report" / "index.html")
    row = index.table(1)[3]
    assert text(row["episode"]) == "room-seed0003"
    assert badge(row["outcome"]) == ("incomplete", "other")
    page = Page(mixed / "report" / "episodes" / "room-seed0003.html")
    (heading,) = lxml.html.fromstring(page.html).xpath("//h1")
    assert badge(heading) == ("no run folder", "other")
    assert "It left no run folder. It counts as incomplete: run the same sweep again" in page.text
    assert not any(tag == "img" for tag, _ in page.tags)
    assert all(target.exists() for target in page.local_targets())


def test_a_sonar_episode_shows_the_sonar_image_beside_each_steps_frames(tmp_path: Path) -> None:
    run_dir = tmp_path / "sonar"
    config = EpisodeConfig(max_steps=2, plots=False, sonar="ping360")
    run_episode(corridor(), ScriptedPilot(("forward 1 m",)), config, run_dir)
    page = Page(write_report(run_dir))
    figures = lxml.html.fromstring(page.html).xpath("//section[@id='step-1']//figure")
    shown = [(f.xpath(".//img/@src")[0], text(f.xpath(".//figcaption")[0])) for f in figures]
    assert shown == [
        ("frames/step_0001_rgb.png", "colour"),
        ("frames/step_0001_depth.png", "depth"),
        ("frames/step_0001_sonar.png", "ping360 sonar"),
    ]
    sonar = [a for tag, a in page.tags if tag == "img" and "sonar" in a["src"]]
    assert len(sonar) == 2 and all(a["class"] == "sonar" for a in sonar)  # as high as the camera's
    assert all(target.exists() for target in page.local_targets())  # linked, as the frames are
