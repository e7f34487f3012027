"""Bad input and faults: each gets one clear line, a documented exit status, and a run
folder that stays valid (docs/guides/faults.md)."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import ConfigError, RecordingError, ScenarioError
from cavenav.episode import run_folder
from cavenav.episode.loop import run_episode
from cavenav.episode.record import EpisodeLog
from cavenav.episode.run_folder import new_run_dir, read_jsonl
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.geometric import GeometricPilot
from cavenav.sensors.rig import SensorConfig
from cavenav.world.scenarios import load_scenario_file, procedural_scenario
from tests.conftest import takes_ctrl_c
from tests.vlm_server import FakeVLM

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def cavenav(*args: str, **kwargs: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cavenav.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        **kwargs,  # type: ignore[arg-type]
    )


def one_error_line(done: subprocess.CompletedProcess[str]) -> str:
    """The single line a refused command prints: no traceback, nothing else."""
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    return lines[0]


# ------------------------------------------------------------------ CLI values


@pytest.mark.parametrize("value", ["0", "-5", "nan", "inf"])
def test_a_depth_range_that_is_not_a_positive_distance_is_refused(value: str) -> None:
    done = cavenav("run", "S1", "--depth-max", value)
    assert done.returncode == 2
    assert "--depth-max" in done.stderr and "Traceback" not in done.stderr
    with pytest.raises(ConfigError, match="D_max"):
        SensorConfig(depth_max_m=float(value))


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_an_option_that_is_not_finite_is_refused(value: str) -> None:
    done = cavenav("run", "S1", "--particles", value)
    assert done.returncode == 2
    assert "Invalid value for '--particles'" in done.stderr


def test_a_negative_seed_is_refused_by_the_command_and_the_library() -> None:
    done = cavenav("run", "S1", "--seed", "-1")
    assert done.returncode == 2 and "--seed" in done.stderr
    with pytest.raises(ScenarioError, match="seed -1"):
        procedural_scenario("S1", seed=-1)


def test_an_out_folder_that_is_a_file_is_refused_before_the_cave_is_built(
    tmp_path: Path,
) -> None:
    taken = tmp_path / "runs"
    taken.write_text("not a folder")
    done = cavenav("run", "S1", "--out", str(taken))
    assert done.returncode == 2
    assert one_error_line(done) == f"error: cannot write run folders into {taken}: it is a file"
    assert "S1:" not in done.stdout  # the cave was never announced, so never built


def test_a_read_only_out_folder_is_refused_before_the_cave_is_built(
    read_only_folder: Path,
) -> None:
    done = cavenav("run", "S1", "--out", str(read_only_folder))
    assert done.returncode == 2
    line = one_error_line(done)
    assert line.startswith(f"error: cannot write run folders into {read_only_folder}: ")
    assert "Permission denied" in line or "Read-only file system" in line
    assert "S1:" not in done.stdout  # refused before the cave was built


# ------------------------------------------------------------------ scenario files


EXIT = "[[exit]]\npoint = [0.0, -10.0, 2.0]\nnormal = [0.0, -1.0, 0.0]\nradius = 3.5"


def scenario_file(
    tmp_path: Path, start: str = "yaw_deg = 0.0", exits: str = EXIT, position: str = "0, 8.5, 2"
) -> Path:
    """The straight OSRF tile with the given [start] lines and exits."""
    mesh = (EXAMPLES / "meshes" / "cave_straight_20m.dae").resolve()
    path = tmp_path / "cave.toml"
    path.write_text(f'mesh = "{mesh}"\n[start]\nposition = [{position}]\n{start}\n{exits}\n')
    return path


@pytest.mark.parametrize(
    ("start", "exits", "message"),
    [
        ("yaw_deg = nan", EXIT, "field 'start.yaw_deg': Input should be a finite number"),
        ("yaw_deg = inf", EXIT, "field 'start.yaw_deg': Input should be a finite number"),
        (
            "yaw_deg = 0.0",
            "[[exit]]\npoint = [0, -5, 0]\nnormal = [0, 0, 0]\nradius = 3.0",
            "field 'exit.0.normal': Value error, exit normal must not be the zero vector",
        ),
        (
            "yaw_deg = 0.0",
            "[[exit]]\npoint = [0, -5, 0]\nnormal = [0, -1, 0]\nradius = -1",
            "field 'exit.0.radius': Input should be greater than 0",
        ),
        (
            "yaw_deg = 0.0",
            "[exit]\npoint = [0, -5, 0]\nnormal = [0, -1, 0]\nradius = -1",
            "field 'exit.radius': Input should be greater than 0",
        ),
    ],
)
def test_a_bad_value_in_a_scenario_file_is_named(
    tmp_path: Path, start: str, exits: str, message: str
) -> None:
    path = scenario_file(tmp_path, start, exits)
    with pytest.raises(ConfigError) as raised:
        load_scenario_file(path)
    assert str(raised.value) == f"{path}: {message}"
    done = cavenav("run", str(path), "--out", str(tmp_path / "runs"))
    assert done.returncode == 2
    assert one_error_line(done) == f"error: {path}: {message}"


# ------------------------------------------------------------------ run folders


def test_runs_started_in_the_same_second_get_folders_of_their_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    class Frozen:  # every run starts in the same second
        @staticmethod
        def now() -> object:
            from datetime import datetime

            return datetime(2026, 11, 23, 4, 0, 0)

    monkeypatch.setattr(run_folder, "datetime", Frozen)
    claimed: list[Path] = []
    threads = [
        threading.Thread(target=lambda: claimed.append(new_run_dir(tmp_path, "S1", "geo", 0)))
        for _ in range(8)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    names = sorted(path.name for path in claimed)
    stem = "20261123-040000_S1_geo_seed0"
    assert names == sorted([stem] + [f"{stem}_{k}" for k in range(2, 9)])
    assert all(path.is_dir() and not any(path.iterdir()) for path in claimed)


def test_a_second_sweep_into_a_folder_in_use_is_refused(tmp_path: Path) -> None:
    from cavenav.evaluation.executors import InProcess
    from cavenav.evaluation.sweep import SweepConfig, run_sweep
    from cavenav.pilots.factory import PilotSpec

    config = SweepConfig(scenarios=("S1",), seeds=(0,), pilot=PilotSpec("geometric"), steps=1)
    folder = tmp_path / "sweep"
    script = (
        "import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDONLY)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "print('HOLDING', flush=True)\n"
        "time.sleep(60)\n"
    )
    folder.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", script, str(folder)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "HOLDING"
        with pytest.raises(ConfigError, match="another sweep is writing into"):
            run_sweep(config, folder, InProcess())
    finally:
        holder.kill()
        holder.wait()
    assert list(folder.iterdir()) == []  # refused before anything was written


def test_a_refused_start_leaves_no_empty_run_folder(tmp_path: Path) -> None:
    path = scenario_file(tmp_path, position="500, 0, 0")
    done = cavenav("run", str(path), "--out", str(tmp_path / "runs"))
    assert done.returncode == 2
    assert "outside the cave" in one_error_line(done)
    assert not (tmp_path / "runs").exists()  # nor the --out folder it made for the run


class DiskFull:
    """A writer that fails with ENOSPC from the ``after``-th call on, like a full disk."""

    def __init__(self, write: object, after: int):
        self.write, self.after, self.calls = write, after, 0

    def __call__(self, *args: object, **kwargs: object) -> object:
        self.calls += 1
        if self.calls > self.after:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.write(*args, **kwargs)  # type: ignore[operator]


def assert_agrees(run_dir: Path, status: str) -> dict:
    """summary.json, steps.jsonl and frames/ tell one story; no temporary is left."""
    summary = json.loads((run_dir / "summary.json").read_text())
    steps = read_jsonl(run_dir / "steps.jsonl")
    assert summary["status"] == status
    assert [s["step"] for s in steps] == list(range(summary["steps"]))
    named = {name for s in steps for name in s.get("frames", {}).values()}
    on_disk = {str(p.relative_to(run_dir)) for p in (run_dir / "frames").glob("*")}
    assert on_disk == named
    assert not list(run_dir.rglob("*.tmp"))
    return summary


def test_a_full_disk_ends_the_run_at_the_last_whole_step(
    room_scenario, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The third step's depth EXR does not fit: its PNGs are taken back with it.
    monkeypatch.setattr(run_folder, "write_exr", DiskFull(run_folder.write_exr, after=2))
    run_dir = tmp_path / "run"
    config = EpisodeConfig(max_steps=10, plots=False)
    with pytest.raises(RecordingError, match="No space left on device"):
        run_episode(room_scenario, GeometricPilot(), config, run_dir)
    summary = assert_agrees(run_dir, "crashed")
    assert summary["steps"] == 2
    assert summary["failure"] == f"cannot write the run folder {run_dir}: No space left on device"


def test_a_disk_that_stays_full_leaves_the_last_summary_which_agrees_with_the_steps(
    room_scenario, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Without frames only summary.json grows a file: its 4th rewrite and every later
    # one (the final "crashed" summary included) find the disk full.
    monkeypatch.setattr(run_folder, "write_json", DiskFull(run_folder.write_json, after=3))
    run_dir = tmp_path / "run"
    config = EpisodeConfig(max_steps=10, plots=False, save_frames=False)
    with pytest.raises(RecordingError):
        run_episode(room_scenario, GeometricPilot(), config, run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "running" and summary["steps"] == 2
    assert [s["step"] for s in read_jsonl(run_dir / "steps.jsonl")] == [0, 1]
    assert not list(run_dir.rglob("*.tmp"))


def test_a_step_lost_after_the_loop_flew_on_is_taken_back_with_those_after_it(
    room_scenario, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Step 0's summary waits on a slow disk, then finds it full: by then the loop has
    # queued the next steps (and waits for room in the queue).
    real_write, calls, disk = run_folder.write_json, [], threading.Event()

    def slow_then_full(*args: object) -> None:
        calls.append(1)
        if len(calls) == 2:
            disk.wait(60)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_write(*args)

    monkeypatch.setattr(run_folder, "write_json", slow_then_full)
    threading.Timer(0.5, disk.set).start()
    run_dir = tmp_path / "run"
    with pytest.raises(RecordingError, match="No space left on device"):
        run_episode(room_scenario, GeometricPilot(), EpisodeConfig(plots=False), run_dir)
    summary = assert_agrees(run_dir, "crashed")
    assert summary["steps"] == 0


def test_a_writer_that_fails_otherwise_ends_the_run_naming_the_error(
    room_scenario, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: object) -> None:
        raise TypeError("cannot write float128 to JSON")

    monkeypatch.setattr(run_folder.RunFolder, "append_step", broken)
    run_dir = tmp_path / "run"
    with pytest.raises(RecordingError, match="TypeError: cannot write float128"):
        run_episode(room_scenario, GeometricPilot(), EpisodeConfig(plots=False), run_dir)
    summary = assert_agrees(run_dir, "crashed")
    assert summary["steps"] == 0 and "TypeError: cannot write float128" in summary["failure"]


def test_ctrl_c_while_the_loop_waits_for_the_writer_keeps_summary_and_steps_equal(
    room_scenario, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_put, calls = run_folder._StepWriter.put, []

    def put(self: object, step: object) -> None:
        calls.append(1)
        if len(calls) == 3:  # Ctrl-C while waiting for room in the queue
            raise KeyboardInterrupt
        real_put(self, step)  # type: ignore[arg-type]

    monkeypatch.setattr(run_folder._StepWriter, "put", put)
    run_dir = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_episode(room_scenario, GeometricPilot(), EpisodeConfig(plots=False), run_dir)
    assert assert_agrees(run_dir, "interrupted")["steps"] == 2


@pytest.mark.slow
def test_the_command_line_says_the_disk_is_full_in_one_line_and_exits_1(
    tmp_path: Path,
) -> None:
    script = (
        "import errno, os, sys\n"
        "from cavenav.episode import run_folder\n"
        "real, calls = run_folder.write_json, []\n"
        "def full(*a, **k):\n"
        "    calls.append(1)\n"
        "    if len(calls) > 3: raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))\n"
        "    return real(*a, **k)\n"
        "run_folder.write_json = full\n"
        "from cavenav.cli import main\n"
        "sys.argv = ['cavenav', *sys.argv[1:]]\n"
        "main()\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, "run", "S1", "--no-frames", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1
    (run_dir,) = tmp_path.iterdir()
    line = one_error_line(done)
    assert line.startswith(f"error: cannot write the run folder {run_dir}: No space left")
    assert line.endswith(f"(the record so far is in {run_dir})")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("slow_part", "flight", "left_out"),
    [
        ("cavenav.episode.plots.plot_episode", ["--steps", "2"], "plots"),
        # The last step is written; the shortest path for SPL is being found.
        ("cavenav.world.geodesic.shortest_path", [], "SPL and plots"),
    ],
)
def test_ctrl_c_after_the_last_step_leaves_a_finished_record_and_exits_130(
    tmp_path: Path, slow_part: str, flight: list[str], left_out: str
) -> None:
    module, _, name = slow_part.rpartition(".")
    script = (
        "import sys, time, importlib\n"
        "def slow(*a, **k):\n"
        "    print('SLOW PART', flush=True)\n"
        "    time.sleep(60)\n"
        f"setattr(importlib.import_module({module!r}), {name!r}, slow)\n"
        "from cavenav.cli import main\n"
        "sys.argv = ['cavenav', *sys.argv[1:]]\n"
        "main()\n"
    )
    args = ["run", "S1", *flight, "--no-frames", "--out", str(tmp_path)]
    process = subprocess.Popen(
        [sys.executable, "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=takes_ctrl_c,
    )
    assert process.stdout is not None
    for line in process.stdout:
        if "SLOW PART" in line:
            break
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130
    (run_dir,) = tmp_path.iterdir()
    assert stderr.strip() == (
        f"interrupted after the episode ended: its record is whole in {run_dir}, without {left_out}"
    )
    summary = json.loads((run_dir / "summary.json").read_text())
    steps = (run_dir / "steps.jsonl").read_text().splitlines()
    assert summary["status"] == "finished" and summary["steps"] == len(steps) > 0
    assert "plots" not in summary
    assert ("spl" in summary) == ("SPL" not in left_out)


@pytest.mark.slow
def test_sigkill_mid_episode_leaves_a_valid_record_that_says_it_is_incomplete(
    tmp_path: Path,
) -> None:
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cavenav.cli",
            "run",
            "S1",
            "--steps",
            "100",
            "--out",
            str(tmp_path),
        ],  # fmt: skip
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            files = list(tmp_path.glob("*/steps.jsonl"))
            if files and len(files[0].read_bytes().splitlines()) >= 3:
                break
            time.sleep(0.05)
        time.sleep(0.07)  # somewhere inside the next step
    finally:
        process.kill()
        process.wait()
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "running" and summary["termination"] is None
    lines = (run_dir / "steps.jsonl").read_text().splitlines()
    steps = [json.loads(line) for line in lines]  # every line whole
    assert [s["step"] for s in steps] == list(range(len(steps)))
    # The kill may fall between a step's line and the summary's rewrite.
    assert summary["steps"] in (len(steps), len(steps) - 1)
    for step in steps:
        for name in step["frames"].values():
            if name.endswith(".png"):
                with Image.open(run_dir / name) as image:
                    assert image.size == (640, 480)
            else:
                assert (run_dir / name).stat().st_size > 0
    named = {name for s in steps for name in s["frames"].values()}
    frames = {str(p.relative_to(run_dir)) for p in (run_dir / "frames").glob("step_*")}
    # Only the step being written when the kill came may have frames without a line.
    unnamed = {Path(name).name[:9] for name in frames - named}
    assert unnamed <= {f"step_{len(steps):04d}"}


# ------------------------------------------------------------------ exit statuses


@pytest.mark.slow
def test_a_pilot_failure_exits_1_with_its_record(tmp_path: Path) -> None:
    with FakeVLM() as server:
        server.persistent_fault = "garbage"
        done = cavenav(
            "run", "S1", "--pilot", "vlm", "--base-url", server.base_url, "--model", "fake",
            "--requeries", "0", "--no-frames", "--out", str(tmp_path),
        )  # fmt: skip
    assert done.returncode == 1, done.stderr
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["termination"] == "pilot_failure" and summary["status"] == "finished"
    assert summary["failure_cause"] == "reply"


def test_the_first_sensing_is_reported_apart_from_the_mean(room_scenario) -> None:
    config = EpisodeConfig()
    log = EpisodeLog(room_scenario, "p", config.rules, False, room_scenario.start, 2.0, config)
    for k, sense in enumerate((900.0, 40.0, 60.0)):  # the first one loaded the kernels
        log.steps.append({"step": k, "timing_ms": {"sense": sense, "pilot": 1.0}})
    summary = log.summary("running")
    assert summary["first_sense_ms"] == 900.0
    assert summary["mean_sense_ms"] == 50.0


# ------------------------------------------------------------------ big meshes


@pytest.mark.parametrize("edge_m", [0.6, 0.15])
def test_the_footprint_raster_covers_what_drawing_each_triangle_covers(edge_m: float) -> None:
    import trimesh
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from cavenav.episode import plots
    from cavenav.world.mesh import make_mesh

    tube = trimesh.creation.cylinder(radius=2.0, height=0.5, sections=64)
    tube = tube.subdivide_to_size(edge_m)  # a disc of radius 2 m seen from above
    mesh = make_mesh(np.asarray(tube.vertices), np.asarray(tube.faces), "tube")

    def covered(draw) -> float:  # noqa: ANN001
        figure = Figure(figsize=(4, 4), dpi=100)
        ax = figure.add_subplot()
        draw(ax)
        ax.set(xlim=(-3, 3), ylim=(-3, 3), aspect="equal")
        ax.axis("off")
        canvas = FigureCanvasAgg(figure)
        canvas.draw()
        return float((np.asarray(canvas.buffer_rgba())[..., :3].mean(axis=2) < 250).mean())

    every_triangle = covered(
        lambda ax: ax.tripcolor(
            *mesh.vertices[:, :2].T,
            mesh.faces,
            facecolors=np.ones(len(mesh.faces)),
            cmap="Greys",
            vmin=0,
            vmax=4,
            edgecolors="none",
        )  # fmt: skip
    )
    raster = covered(lambda ax: plots.draw_footprint(ax, mesh))
    assert every_triangle > 0.05  # the disc is drawn
    assert raster == pytest.approx(every_triangle, rel=0.03)


@pytest.mark.parametrize("cells", [40, 400])  # triangles within 2 cells, and far larger
def test_the_footprint_raster_of_a_disc_is_the_disc_without_holes(cells: int) -> None:
    import trimesh

    from cavenav.episode.plots import footprint_raster
    from cavenav.world.mesh import make_mesh

    disc = trimesh.creation.cylinder(radius=2.0, height=0.5, sections=64).subdivide_to_size(0.1)
    mesh = make_mesh(np.asarray(disc.vertices), np.asarray(disc.faces), "disc")
    covered, (left, right, bottom, top) = footprint_raster(mesh, cells=cells)
    cell = (right - left) / covered.shape[0]
    x = left + (np.arange(covered.shape[0]) + 0.5) * cell
    y = bottom + (np.arange(covered.shape[1]) + 0.5) * cell
    radius = np.hypot(*np.meshgrid(x, y, indexing="ij"))
    assert covered[radius < 2.0 - 2 * cell].all()  # no holes inside
    assert not covered[radius > 2.0 + 2 * cell].any()  # nothing outside
    assert covered.sum() * cell**2 == pytest.approx(np.pi * 2.0**2, rel=0.1)


# ------------------------------------------------------------------ the first run


def test_the_warm_up_compiles_every_cached_kernel_so_no_step_has_to() -> None:
    # In a fresh process, as `make setup` runs it: a kernel it missed would be compiled
    # inside a newcomer's first step instead (about a minute).
    script = (
        "import numba.extending\n"
        "from cavenav.pilots import geometric\n"
        "from cavenav.sensors import kernels\n"
        "from cavenav.episode.warmup import warm_up\n"
        "warm_up()\n"
        "for name, f in [*vars(kernels).items(), *vars(geometric).items()]:\n"
        # Kernels that take turns (Numba's work queue) wrap the dispatcher.
        "    f = f if numba.extending.is_jitted(f) else getattr(f, '__wrapped__', f)\n"
        # A dispatcher's documented stats name its cache's folder; None when uncached.
        "    if numba.extending.is_jitted(f) and f.stats.cache_path is not None:\n"
        "        print(name, len(f.signatures))\n"
    )
    for _ in range(2):  # the second time, the box's lighting table is on disk already
        done = subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0, done.stderr
    compiled = dict(line.split() for line in done.stdout.splitlines())
    assert {"shade_frame", "shade_grid", "splat_particles", "free_lengths"} <= compiled.keys()
    assert [name for name, count in compiled.items() if count == "0"] == []
