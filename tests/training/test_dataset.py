"""Flights become training data (`cavenav dataset`): one row a decision, its request
byte for byte as the VLM pilot sends it, split by cave, written so that a stopped export
never looks whole."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from cavenav.core.errors import ConfigError, RecordingError
from cavenav.core.types import Decision, Observation
from cavenav.episode.loop import run_episode
from cavenav.episode.run_folder import read_jsonl
from cavenav.episode.settings import EpisodeConfig
from cavenav.evaluation.executors import InProcess
from cavenav.evaluation.sweep import SweepConfig, run_sweep
from cavenav.pilots.backends import Completion
from cavenav.pilots.factory import PilotSpec, VLMOptions
from cavenav.pilots.geometric import GeometricPilot
from cavenav.pilots.random_pilot import RandomPilot
from cavenav.pilots.shadow import ShadowedPilot
from cavenav.pilots.vlm import VLMPilot
from cavenav.training.dataset import (
    DatasetOptions,
    export_dataset,
    request_messages,
    target_reply,
)
from cavenav.world.scenarios import load_scenario
from tests.conftest import cavenav, full_disk
from tests.pilots.test_vlm import pilot_for
from tests.vlm_server import FakeVLM

QUICK = EpisodeConfig(max_steps=4, save_frames=False, plots=False)


def patient_pilot(server: FakeVLM) -> VLMPilot:
    """`pilot_for` that waits out a busy machine: a request timed out and sent again
    reaches the server twice, and the requests it got no longer pair with the steps."""
    return pilot_for(server, timeout_s=30.0)


def rows_of(out: Path, split: str = "train") -> list[dict]:
    """Every row of a split, as pyarrow reads it (images as their bytes)."""
    return [row for path in sorted((out / "data").glob(f"{split}-*.parquet"))
            for row in pq.read_table(path).to_pylist()]  # fmt: skip


def as_json(messages: list[dict]) -> str:
    return json.dumps(messages, sort_keys=True)


@pytest.mark.slow
def test_a_vlm_runs_rows_hold_the_very_messages_it_sent(tmp_path: Path) -> None:
    """Done when: byte for byte against exchanges.jsonl, and against what the server got."""
    run_dir = tmp_path / "run"
    with FakeVLM() as server:
        run_episode(load_scenario("S4"), patient_pilot(server), QUICK, run_dir)
        sent = [request["messages"] for request in server.requests]
    out = tmp_path / "data"
    export_dataset([run_dir], out, DatasetOptions(episodes="all", validation=0))
    rows = rows_of(out)
    exchanges = read_jsonl(run_dir / "exchanges.jsonl")
    assert [row["step"] for row in rows] == [0, 1, 2, 3] and len(exchanges) == 4
    for row, exchange, wire in zip(rows, exchanges, sent, strict=True):
        stored = [
            {**m, "content": [
                {"type": "image_url", "image_url": {"url": _url(run_dir / p["file"])}}
                if p["type"] == "image" else p for p in m["content"]
            ]} if isinstance(m["content"], list) else m
            for m in exchange["messages"]
        ]  # fmt: skip
        assert as_json(request_messages(row)) == as_json(stored) == as_json(wire)
        assert row["reply"] == exchange["reply"]  # the model's own words, reasoning and all
        assert row["teacher"] == row["pilot"] == "vlm:fake-vlm"


def _url(path: Path) -> str:
    import base64

    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode()


class AskingAlong:
    """The geometric pilot steers; a VLM pilot is asked at every step and told the
    geometric pilot's answer: what it sends is what a VLM pilot flying these moves sends."""

    name = "geometric"

    def __init__(self, options: VLMOptions):
        self.geometric = GeometricPilot()
        self.sent: list[list[dict]] = []
        self.reply, self.model = "", "script"
        self.vlm = VLMPilot(self, options.prompt_config(), check=False,
                            images=options.request_images())  # fmt: skip

    def check(self) -> None: ...

    def complete(self, messages: list[dict], json_schema: dict | None = None) -> Completion:
        self.sent.append(messages)
        return Completion(self.reply)

    def reset(self) -> None:
        self.geometric.reset()
        self.vlm.reset()

    def decide(self, observation: Observation) -> Decision:
        decision = self.geometric.decide(observation)
        self.reply = target_reply(decision.action_text, decision.justification)
        assert self.vlm.decide(observation).action == decision.action
        return decision


@pytest.mark.slow
def test_a_geometric_flight_is_asked_again_as_a_vlm_pilot_flying_it_would_ask(
    tmp_path: Path,
) -> None:
    """No frames are kept: the episode is flown again, and its sensor noise, marine snow,
    history and images at the asked size come out as they were."""
    options = VLMOptions(image_size="128x96", image_format="jpeg", history=1)
    along = AskingAlong(options)
    run_dir = tmp_path / "run"
    run_episode(load_scenario("S1", 3), along, QUICK, run_dir)
    out = tmp_path / "data"
    export_dataset([run_dir], out, DatasetOptions(episodes="all", validation=0, vlm=options))
    rows = rows_of(out)
    assert len(rows) == len(along.sent) == 4
    for row, sent in zip(rows, along.sent, strict=True):
        assert as_json(request_messages(row)) == as_json(sent)
        assert [image["bytes"][:2] for image in row["images"]][:2] == [b"\xff\xd8", b"\x89P"]
    first = rows[0]
    assert first["reply"].startswith("(a) Situation: ")  # its reasoning, then the dictionary
    assert json.loads(first["reply"].splitlines()[-1]) == {
        first["action"]: json.loads(first["reply"].splitlines()[-1])[first["action"]]
    }


def test_the_geometric_pilots_reply_reads_as_reasoning_then_one_pair() -> None:
    why = (
        "Situation: the passage continues 20.0 m toward 3 deg down; free straight ahead "
        "20.0 m. Constraints: all clearances above the 2.0 m standoff. Choice: forward 1 m, "
        "holding the passage centre."
    )
    full = target_reply("forward 1 m", why)
    assert full.splitlines()[:3] == [
        "(a) Situation: the passage continues 20.0 m toward 3 deg down; free straight ahead "
        "20.0 m.",
        "(b) Constraints: all clearances above the 2.0 m standoff.",
        "(c) Choice: forward 1 m, holding the passage centre.",
    ]
    brief = {"forward 1 m": "all clearances above the 2.0 m standoff; holding the passage centre"}
    assert json.loads(full.splitlines()[-1]) == brief
    assert json.loads(target_reply("forward 1 m", why, "brief")) == brief
    assert json.loads(target_reply("hold", "too close")) == {"hold": "too close"}  # other pilots
    terse = {"forward 1 m": "holding the passage centre"}
    assert json.loads(target_reply("forward 1 m", why, "terse")) == terse
    bare = why.replace(", holding the passage centre", "")  # a choice without a reason
    assert json.loads(target_reply("forward 1 m", bare, "terse")) == {
        "forward 1 m": "all clearances above the 2.0 m standoff"
    }
    assert json.loads(target_reply("hold", "too close", "terse")) == {"hold": "too close"}


@pytest.mark.slow
def test_teacher_labels_train_on_the_students_own_states(tmp_path: Path) -> None:
    """DAgger: the random pilot flies, the geometric pilot labels what it would have done
    at each state the random pilot reached; the history shows the moves actually made."""
    run_dir = tmp_path / "run"
    pilot = ShadowedPilot(RandomPilot(5), GeometricPilot())
    result = run_episode(load_scenario("S1"), pilot, QUICK, run_dir)
    assert result.summary["pilot_seed"] == 5  # the student's draws, recorded
    flown = [step["action"] for step in result.steps]
    with pytest.raises(ConfigError, match="no teacher label"):  # a model flown alone
        bare = tmp_path / "bare"
        with FakeVLM() as server:
            run_episode(load_scenario("S1"), patient_pilot(server), QUICK, bare)
        export_dataset([bare], tmp_path / "nothing", DatasetOptions(labels="teacher"))
    out = tmp_path / "data"
    export_dataset([run_dir], out, DatasetOptions(labels="teacher", validation=0))
    rows = rows_of(out)  # every episode by default with teacher labels: where it went wrong
    assert [row["action"] for row in rows] == [s["teacher"]["action"] for s in result.steps]
    assert all(row["teacher"] == "geometric" and row["pilot"] == "random" for row in rows)
    last = request_messages(rows[-1])[1]["content"]
    taken = [p["text"].removeprefix("Action taken after it: ") for p in last
             if p["type"] == "text" and p["text"].startswith("Action taken")]  # fmt: skip
    assert taken == flown[-3:-1]  # the student's moves, not the teacher's
    # DAgger's dataset: the round above and the teacher's own flight, its own teacher.
    alone = tmp_path / "alone"
    run_episode(load_scenario("S1", 1), GeometricPilot(), QUICK, alone)
    both = tmp_path / "both"
    export_dataset([run_dir, alone], both, DatasetOptions(labels="teacher", validation=0))
    assert [row["teacher"] for row in rows_of(both)] == ["geometric"] * 8
    assert [row["pilot"] for row in rows_of(both)] == ["random"] * 4 + ["geometric"] * 4
    # A model's round, its requests as recorded, goes with the teacher's flight too: that
    # flight had no prompt, and is asked again with the dataset's.
    student = tmp_path / "student"
    with FakeVLM() as server:
        shadowed = ShadowedPilot(patient_pilot(server), GeometricPilot())
        run_episode(load_scenario("S1"), shadowed, QUICK, student)
    rounds = DatasetOptions(labels="teacher", validation=0)
    assert export_dataset([student, alone], tmp_path / "rounds", rounds).episodes == 2


@pytest.mark.slow
def test_a_sweep_is_split_by_cave_and_loads_with_datasets(tmp_path: Path) -> None:
    import datasets

    sweep = tmp_path / "sweep"
    config = SweepConfig(("S1",), (0, 1, 2, 3), PilotSpec(), steps=2, frames="none")
    run_sweep(config, sweep, InProcess())
    out = tmp_path / "data"
    done = export_dataset([sweep], out, DatasetOptions(episodes="all", validation=0.25))
    train, validation = rows_of(out), rows_of(out, "validation")
    assert done.rows == {"train": len(train), "validation": len(validation)} == {
        "train": 6, "validation": 2}  # fmt: skip
    assert not {r["cave"] for r in train} & {r["cave"] for r in validation}
    assert {r["cave"] for r in validation} == set(done.card["validation_caves"])
    loaded = datasets.load_dataset(str(out))
    assert loaded["train"].num_rows == 6 and loaded["validation"].num_rows == 2
    assert loaded["train"][0]["images"][0].size == (640, 480)
    card = (out / "README.md").read_text()
    assert "| rows | train 6, validation 2 |" in card and str(sweep) in card
    # Successful episodes only by default: 2 steps reach no exit.
    with pytest.raises(ConfigError, match="unsuccessful 4"):
        export_dataset([sweep], tmp_path / "none")


@pytest.mark.slow
def test_a_recording_that_does_not_fly_again_is_refused(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    run_episode(load_scenario("S1"), GeometricPilot(), QUICK, run_dir)
    lines = (run_dir / "steps.jsonl").read_text().splitlines()
    moved = json.loads(lines[2])
    moved["pose"]["x"] += 0.01
    lines[2] = json.dumps(moved)
    (run_dir / "steps.jsonl").write_text("\n".join(lines) + "\n")
    out = tmp_path / "data"
    with pytest.raises(ConfigError, match="step 2 does not fly again where it was recorded"):
        export_dataset([run_dir], out, DatasetOptions(episodes="all", shard_rows=1))
    assert not out.exists()  # the shards of steps 0 and 1 are gone with it


@pytest.mark.slow
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path) -> None:
    runs, cave = [tmp_path / "clear", tmp_path / "turbid"], load_scenario("S1")
    for run_dir in runs:
        settings = EpisodeConfig(max_steps=2, save_frames=False, optics={"water": run_dir.name})
        run_episode(cave, GeometricPilot(), settings, run_dir)
    out, every = tmp_path / "out", DatasetOptions(episodes="all")
    refused = {
        "neither a sweep folder": ([tmp_path / "nowhere"], every),
        "different settings or prompts": (runs, every),
    }
    for message, (sources, options) in refused.items():
        with pytest.raises(ConfigError, match=message):
            export_dataset(sources, out, options)
    with pytest.raises(ConfigError, match="--labels must be one of"):
        DatasetOptions(labels="oracle")
    assert not out.exists()
    # On the command line: one line, exit 2, nothing written.
    done = cavenav("dataset", *map(str, runs), "--episodes", "all", "--out", str(out))
    assert done.returncode == 2 and "different settings or prompts" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not out.exists()
    mixed = export_dataset(runs, out, replace(every, allow_mixed=True))
    assert mixed.rows == {"train": 4, "validation": 0} and mixed.episodes == 2
    with pytest.raises(ConfigError, match="not an empty folder"):
        export_dataset(runs[:1], out, every)


@pytest.mark.slow
def test_a_full_disk_leaves_no_shard_or_card_that_looks_whole(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    run_episode(load_scenario("S1"), GeometricPilot(), QUICK, run_dir)
    with full_disk(tmp_path / "disk", "64k") as disk:
        options = DatasetOptions(episodes="all", shard_rows=1)  # a shard a row: 4 writes
        with pytest.raises(RecordingError, match="No space left"):
            export_dataset([run_dir], disk / "data", options)
        assert not [p.name for p in (disk / "data").rglob("*") if p.is_file()]


def test_a_sweeps_teacher_is_kept_in_sweep_json_and_absent_without_one() -> None:
    taught = SweepConfig(("S1",), (0,), PilotSpec("random", teacher="geometric"))
    assert taught.to_dict()["pilot"]["teacher"] == "geometric"
    assert SweepConfig.from_dict(taught.to_dict()).pilot.teacher == "geometric"
    assert "teacher" not in SweepConfig(("S1",), (0,), PilotSpec()).to_dict()["pilot"]
    assert isinstance(taught.pilot.build(seed=3), ShadowedPilot)
    with pytest.raises(ConfigError, match="unknown teacher 'vlm'"):
        PilotSpec("random", teacher="vlm")
