"""Episode videos: one H.264 frame per step, colour | depth | map, read back as a player would.

Episodes are flown in the 20 m test corridor (fast); the S1-S5 map background is checked
by rebuilding a family cave from its summary fields.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import (
    CavenavError,
    CavenavWarning,
    ConfigError,
    DependencyError,
    RecordError,
    RecordingError,
)
from cavenav.episode.loop import run_episode
from cavenav.episode.settings import EpisodeConfig
from cavenav.episode.video import (
    CAPTION_HEIGHT,
    PANEL_HEIGHT,
    REASON_LINES,
    REASON_TOP,
    _rebuild_scenario,
    write_video,
)
from cavenav.pilots.geometric import GeometricPilot
from cavenav.world.scenarios import load_scenario
from tests.conftest import cavenav, full_disk
from tests.evaluation.test_report import INTO_THE_WALL, ScriptedPilot, corridor

STEPS = 6
CAMERA = (640, 480)  # the default camera: panels 640 + 640 + a 480 px square map


@pytest.fixture(scope="module")
def forward_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six 1 m moves down the test corridor (along -y), frames saved."""
    run_dir = tmp_path_factory.mktemp("video") / "forward"
    config = EpisodeConfig(max_steps=STEPS, plots=False)
    run_episode(corridor(), ScriptedPilot(("forward 1 m",)), config, run_dir)
    return run_dir


def read_video(path: Path) -> tuple[tuple[int, int], float, list[np.ndarray]]:
    """(width, height), fps and every decoded frame as (h, w, 3) uint8."""
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    width, height = meta["size"]
    frames = [np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader]
    return (width, height), meta["fps"], frames


def vehicle_centre(frame: np.ndarray) -> np.ndarray:
    """(row, col) of the red vehicle arrow inside the map panel (right of the two images)."""
    map_panel = frame[:PANEL_HEIGHT, 2 * CAMERA[0] :].astype(int)
    red = (map_panel[..., 0] > 170) & (map_panel[..., 1] < 90) & (map_panel[..., 2] < 90)
    assert red.sum() > 20, "no vehicle marker on the map"
    return np.argwhere(red).mean(axis=0)


def test_a_video_has_one_frame_per_step_at_the_documented_size(forward_run: Path) -> None:
    out = write_video(forward_run)
    assert out == forward_run / "episode.mp4"
    size, fps, frames = read_video(out)
    assert len(frames) == STEPS
    assert size == (2 * CAMERA[0] + PANEL_HEIGHT, PANEL_HEIGHT + CAPTION_HEIGHT) == (1760, 512)
    assert fps == pytest.approx(4.0)
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    reader.close()
    # H.264 in 4:2:0, what every browser and player decodes.
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["duration"] == pytest.approx(STEPS / 4.0, abs=0.01)


def test_the_vehicle_moves_down_the_map_as_it_heads_along_minus_y(
    forward_run: Path, tmp_path: Path
) -> None:
    _, fps, frames = read_video(write_video(forward_run, tmp_path / "fast.mp4", fps=10))
    assert fps == pytest.approx(10.0)
    first, last = vehicle_centre(frames[0]), vehicle_centre(frames[-1])
    assert last[0] > first[0] + 5  # image rows grow downward, like -y on the map
    assert abs(last[1] - first[1]) < 5


def test_a_run_flown_without_frames_is_refused_in_one_line(tmp_path: Path) -> None:
    run_dir = tmp_path / "noframes"
    config = EpisodeConfig(max_steps=2, save_frames=False, plots=False)
    run_episode(corridor(), GeometricPilot(), config, run_dir)
    with pytest.raises(CavenavError) as error:
        write_video(run_dir)
    message = str(error.value)
    assert "\n" not in message and "no frames" in message and "frames saved" in message
    assert not (run_dir / "episode.mp4").exists()


def test_without_imageio_ffmpeg_the_error_says_how_to_install_it(
    forward_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # import now fails
    with pytest.raises(DependencyError, match="pip install imageio-ffmpeg"):
        write_video(forward_run, tmp_path / "x.mp4")


def test_a_cave_that_cannot_be_rebuilt_still_gets_a_video_of_its_path(tmp_path: Path) -> None:
    run_dir = tmp_path / "room"
    result = run_episode(corridor(), ScriptedPilot(INTO_THE_WALL), EpisodeConfig(), run_dir)
    assert result.termination == "collision"  # the last frame shows the crash
    size, _, frames = read_video(write_video(run_dir))
    assert len(frames) == result.summary["steps"] == 3
    assert size == (1760, 512)


def test_the_map_shows_the_flown_cave_only_when_it_rebuilds_to_the_same_mesh() -> None:
    s4 = {"scenario": "S4", "seed": 3, "mesh": "S4-seed3"}
    rebuilt = _rebuild_scenario(s4)
    assert rebuilt is not None and rebuilt.mesh.name == "S4-seed3"
    assert rebuilt.mesh.triangle_count == load_scenario("S4", 3).mesh.triangle_count
    assert _rebuild_scenario({**s4, "mesh": "S4-seed3-d0123abcd"}) is None  # harder knobs
    assert _rebuild_scenario({**s4, "scenario": "room"}) is None  # not a family: path only
    assert _rebuild_scenario({**s4, "seed": None}) is None


def test_an_out_that_is_a_folder_or_under_a_file_is_refused_in_one_line(
    forward_run: Path, tmp_path: Path
) -> None:
    (tmp_path / "a-file").write_text("")
    for out, says in (
        (tmp_path, f"{tmp_path} is a folder: name the MP4 to write, e.g. {tmp_path}/episode.mp4"),
        (tmp_path / "a-file" / "v.mp4", f"cannot write {tmp_path}/a-file/v.mp4: "
         f"{tmp_path}/a-file is a file, not a folder"),
    ):  # fmt: skip
        with pytest.raises(ConfigError) as error:
            write_video(forward_run, out)
        assert str(error.value) == says and error.value.exit_status == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]  # nothing written


def test_the_command_line_refuses_a_folder_for_out_in_one_line(
    forward_run: Path, tmp_path: Path
) -> None:
    done = cavenav("video", str(forward_run), "--out", str(tmp_path))
    assert done.returncode == 2
    assert done.stderr == f"error: {tmp_path} is a folder: name the MP4 to write, e.g. " + (
        f"{tmp_path}/episode.mp4\n"
    )


def test_a_read_only_out_folder_is_one_line_and_leaves_no_part_of_a_video(
    forward_run: Path, read_only_folder: Path
) -> None:
    with pytest.raises(RecordingError) as error:
        write_video(forward_run, read_only_folder / "v.mp4")
    message = str(error.value)
    assert message.startswith(f"cannot write {read_only_folder}/v.mp4: ")
    assert message.endswith(("Permission denied", "Read-only file system"))
    assert error.value.exit_status == 1
    assert list(read_only_folder.iterdir()) == []


def test_a_missing_or_cut_short_frame_is_a_grey_panel_with_a_warning_naming_the_step(
    forward_run: Path, tmp_path: Path
) -> None:
    run_dir = tmp_path / "damaged"
    shutil.copytree(forward_run, run_dir)
    rgb = run_dir / "frames" / "step_0001_rgb.png"
    rgb.write_bytes(rgb.read_bytes()[:300])  # the header survives, the pixels do not
    (run_dir / "frames" / "step_0003_depth.png").unlink()
    with pytest.warns(CavenavWarning) as warned:
        video = write_video(run_dir)
    cut, missing = (str(w.message) for w in warned)
    # Pillow's own words follow, with how much it could not read where it says so
    assert cut.startswith(
        f"{run_dir}: step 1: frames/step_0001_rgb.png cannot be read (image file is truncated"
    ) and cut.endswith("; shown as a grey panel")
    assert (
        missing
        == f"{run_dir}: step 3: frames/step_0003_depth.png is missing; shown as a grey panel"
    )
    _, _, frames = read_video(video)
    assert len(frames) == STEPS  # the video is still made, a frame for every step
    grey = np.array([60, 60, 60])
    # under the panel's label and the justification over the top of the colour panel
    below_label = slice(REASON_TOP + 17 * REASON_LINES + 8, PANEL_HEIGHT)
    for k, panel in ((1, slice(0, CAMERA[0])), (3, slice(CAMERA[0], 2 * CAMERA[0]))):
        assert np.abs(frames[k][below_label, panel].astype(int) - grey).max() <= 6  # H.264
    assert np.abs(frames[2][below_label, : 2 * CAMERA[0]].astype(int) - grey).max() > 30


@pytest.mark.parametrize(
    ("name", "text", "says"),
    [
        ("summary.json", "[1, 2]", "summary.json: holds an array, not a JSON object"),
        ("summary.json", '{"exits": 3}', "summary.json: field 'exits': Input should be"),
        ("steps.jsonl", '{"step": "first"}', "steps.jsonl line 1: field 'step': Input should be"),
    ],
)
def test_a_damaged_record_is_one_line_naming_the_file_and_the_field(
    forward_run: Path, tmp_path: Path, name: str, text: str, says: str
) -> None:
    run_dir = tmp_path / "damaged"
    shutil.copytree(forward_run, run_dir, ignore=shutil.ignore_patterns("*.mp4"))
    (run_dir / name).write_text(text)
    with pytest.raises(RecordError) as error:
        write_video(run_dir)
    assert str(error.value).startswith(f"{run_dir}/{says}") and "\n" not in str(error.value)
    assert not (run_dir / "episode.mp4").exists()


def test_a_full_disk_is_one_line_and_leaves_no_part_of_a_video(
    forward_run: Path, tmp_path: Path
) -> None:
    # x264 holds a short episode back until its input closes: the disk fills at the end.
    with full_disk(tmp_path / "disk", "40k") as disk:
        with pytest.raises(RecordingError) as error:
            write_video(forward_run, disk / "v.mp4")
        assert str(error.value) == f"cannot write {disk}/v.mp4: No space left on device"
        assert error.value.exit_status == 1
        assert list(disk.iterdir()) == []


def test_a_sonar_episode_shows_the_sonar_image_between_the_depth_and_the_map(
    tmp_path: Path,
) -> None:
    run_dir = tmp_path / "sonar"
    config = EpisodeConfig(max_steps=2, plots=False, sonar="multibeam")
    run_episode(corridor(), ScriptedPilot(("forward 1 m",)), config, run_dir)
    size, _, frames = read_video(write_video(run_dir))
    # The multibeam's 726 x 400 fan is 871 px wide at the panel height; H.264 wants even.
    sonar_width = round(726 * PANEL_HEIGHT / 400)
    assert size == (2 * CAMERA[0] + sonar_width + PANEL_HEIGHT + 1, 512) == (2632, 512)
    below_label = slice(REASON_TOP, PANEL_HEIGHT)
    for k, frame in enumerate(frames):
        with Image.open(run_dir / "frames" / f"step_{k:04d}_sonar.png") as png:
            assert png.mode == "L" and png.size == (726, 400)
            scaled = png.convert("RGB").resize((sonar_width, PANEL_HEIGHT))
        want = np.asarray(scaled, int)[below_label]
        got = frame[below_label, 2 * CAMERA[0] : 2 * CAMERA[0] + sonar_width].astype(int)
        assert (want > 60).mean() > 0.002  # the fan shows the corridor's walls
        assert np.abs(got - want).mean() < 2 and np.corrcoef(got.ravel(), want.ravel())[0, 1] > 0.95
        assert vehicle_centre(frame)[1] > sonar_width  # the map comes after the sonar
