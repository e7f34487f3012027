"""Shared fixtures: small exact geometries whose answers are known by hand."""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cavenav.core.types import Action, Observation, Pose
from cavenav.motion.kinematics import Drift, apply
from cavenav.sensors.depth import normalise_depth
from cavenav.world.mesh import CaveMesh, make_mesh
from cavenav.world.scenarios import ExitPortal, Scenario

# Tests never reach a model hub: whatever they load, they built themselves.
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["TRANSFORMERS_OFFLINE"] = "1"


# The procedural-cave mesh cache (`cavenav.world.procedural.cache_dir`) is a folder of this
# test session's own: tests neither read meshes a user's ~/.cache/cavenav holds nor leave
# theirs there, and each cave is built once per session. It is set here, at import, before
# any test module copies the environment, so the commands and worker processes the tests
# start share it; a child process that imports this file again keeps its parent's folder.
# Set CAVENAV_TEST_CACHE to a folder to keep the test caves from one session to the next.
# (numba's kernel cache is left alone: it lives in the package's __pycache__, and a fresh
# one would cost every session minutes of compiling.)
def _session_cave_cache() -> str:
    if not os.environ.get("CAVENAV_TEST_CACHE"):
        folder = tempfile.mkdtemp(prefix="cavenav-test-caves-")
        os.environ["CAVENAV_TEST_CACHE"] = folder
        owner = os.getpid()

        def remove() -> None:  # by the session's process only, not by a child of it
            if os.getpid() == owner:
                shutil.rmtree(folder, ignore_errors=True)

        atexit.register(remove)
    return os.environ["CAVENAV_TEST_CACHE"]


os.environ["CAVENAV_CACHE"] = _session_cave_cache()


def box_room(extents=(4.0, 20.0, 4.0), centre=(0.0, 0.0, 0.0)) -> CaveMesh:
    """A closed rectangular room: walls at +-x/2, +-y/2, +-z/2 around ``centre``."""
    box = trimesh.creation.box(extents=extents)
    return make_mesh(box.vertices + np.asarray(centre), box.faces, "box-room")


def wide() -> dict[str, str]:
    """The environment, with a terminal wide enough that a table row prints on one line."""
    return {**os.environ, "COLUMNS": "240"}


def cavenav(
    *args: str, cwd: Path | None = None, env: Mapping[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """Run the command line as a user would, in a fresh process (``env``: its whole
    environment, `wide` by default)."""
    return subprocess.run(
        [sys.executable, "-m", "cavenav.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
        env=wide() if env is None else dict(env),
    )


def flying(out: Path, count: int, steps: int = 1, deadline_s: float = 120) -> dict[str, int]:
    """Wait until ``count`` episodes of the sweep in ``out`` are in the air, each with at
    least ``steps`` steps flown; their names and the pids of the processes flying them."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        found = {}
        for summary in out.glob("episodes/*/summary.json"):
            try:
                record = json.loads(summary.read_text())
            except ValueError:
                continue  # being rewritten
            if record["status"] == "running" and record["steps"] >= steps:
                found[summary.parent.name] = record["pid"]
        if len(found) >= count:
            return found
        time.sleep(0.05)
    raise AssertionError(f"fewer than {count} episodes flew {steps} steps within {deadline_s} s")


def takes_ctrl_c() -> None:
    """``preexec_fn`` for a command a test interrupts with SIGINT: Ctrl-C as a terminal
    gives it, even when the tests themselves run with SIGINT ignored (a shell starts its
    background jobs so, and an ignored signal stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def write_room(folder: Path, start_y: float = 8.0) -> Path:
    """A scenario file: a closed 8 x 20 x 7 m hall, exit 2 m before its far wall."""
    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(8.0, 20.0, 7.0)).export(folder / "room.ply")
    path = folder / f"room{'' if start_y == 8.0 else '-bad'}.toml"
    path.write_text(
        '# a test corridor\nmesh = "room.ply"\n'
        f"[start]\nposition = [0.0, {start_y}, 0.0]\n"
        "[[exit]]\npoint = [0.0, -6.0, 0.0]\nnormal = [0.0, -1.0, 0.0]\nradius = 3.0\n"
    )
    return path


def _mount(*arguments: str | Path) -> str:
    """Run mount(8) with ``arguments``: what it said when it refused, "" when it mounted."""
    done = subprocess.run(["mount", *map(str, arguments)], capture_output=True, text=True)
    return "" if done.returncode == 0 else done.stderr.strip() or f"exit {done.returncode}"


@contextlib.contextmanager
def read_only(folder: Path) -> Iterator[Path]:
    """``folder``, with what it holds, refusing every write while the context lasts, root
    included (CI runs as root, who writes through permission bits): as root the folder is
    bind-mounted read-only onto itself, as another user its folders lose their write bits.
    """
    if os.geteuid() != 0:
        folders = [folder, *(p for p in folder.rglob("*") if p.is_dir())]
        for each in folders:
            each.chmod(0o555)
        try:
            yield folder
        finally:
            for each in folders:
                each.chmod(0o755)
        return
    for arguments in (["--bind", folder, folder], ["-o", "remount,ro,bind", folder]):
        if refused := _mount(*arguments):
            pytest.fail(f"as root, read-only means a read-only mount: {refused}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@contextlib.contextmanager
def full_disk(folder: Path, size: str) -> Iterator[Path]:
    """``folder`` made a disk of ``size`` ("96k") of its own while the context lasts (a
    tmpfs): what is written into it past that fails with ENOSPC. Mounting needs root: as
    root (CI) a failed mount fails the test, as another user the test is skipped."""
    folder.mkdir(parents=True, exist_ok=True)
    if refused := _mount("-t", "tmpfs", "-o", f"size={size}", "tmpfs", folder):
        if os.geteuid() == 0:
            pytest.fail(f"as root, a full disk is a small tmpfs: {refused}")
        pytest.skip(f"a {size} tmpfs needs root (mount): the full disk is not tested here")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)


@pytest.fixture
def read_only_folder(tmp_path: Path) -> Iterator[Path]:
    """An empty folder nobody can write into (see `read_only`)."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    with read_only(folder):
        yield folder


@pytest.fixture
def room() -> CaveMesh:
    return box_room()


@pytest.fixture
def room_scenario(room: CaveMesh) -> Scenario:
    """A 20 m corridor, 4 m square, start near +y heading -y, exit just before the -y wall."""
    return Scenario(
        name="room",
        mesh=room,
        start=Pose(0.0, 8.0, 0.0, 0.0),
        exits=(ExitPortal((0.0, -6.0, 0.0), (0.0, -1.0, 0.0), 3.0),),
        description="test corridor",
    )


def synthetic_observation(
    depth_m: float | np.ndarray, d_top: float = 3.0, d_bottom: float = 3.0, **fields: object
) -> Observation:
    """A 640x480 observation with the simulator's camera, seeing ``depth_m`` everywhere."""
    depth = np.broadcast_to(np.float32(depth_m), (480, 640)).astype(np.float32)
    return Observation(
        rgb=np.zeros((480, 640, 3), np.uint8),
        depth_m=depth,
        depth_png=normalise_depth(depth),
        d_top=d_top,
        d_bottom=d_bottom,
        depth_range=(0.0, 20.0),
        hfov_deg=53.13,
        camera_offset_m=0.2,
        **fields,
    )


class Overshooting:
    """A stand-in vehicle (a `Motion`) that flies every move 10% too far, and reports
    the drift."""

    def start(self, pose: Pose) -> Pose:
        return pose

    def move(self, pose: Pose, action: Action) -> Pose:
        return apply(pose, replace(action, forward=1.1 * action.forward))

    def drift(self, pose: Pose, action: Action, reached: Pose) -> Drift:
        return Drift.of(pose, action, reached)
