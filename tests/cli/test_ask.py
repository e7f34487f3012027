"""`cavenav ask` with photographs as users bring them: too big, sideways, without depth,
with a depth image of another size. Checked on the request the model server received."""

from __future__ import annotations

import base64
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.pilots.photo import model_size, shrink_depth
from tests.vlm_server import FakeVLM


class PhotoVLM(FakeVLM):
    """The fake server, answering the same admissible action to whatever it is shown
    (its usual answer reads a depth image, which these requests may lack)."""

    def answer(self, body: dict) -> str:
        return 'I see rock ahead.\n{"turn left 15 deg": "wall ahead, more room on the left"}'


@pytest.fixture
def server():
    with PhotoVLM() as fake:
        yield fake


def ask(server: FakeVLM, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cavenav.cli", "ask", *args, "--base-url", server.base_url,
         "--model", "fake-vlm", "--retries", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )  # fmt: skip


def sent(server: FakeVLM) -> tuple[list[Image.Image], list[str]]:
    """The images (decoded) and the texts of the one request the server received."""
    (request,) = server.requests
    content = request["messages"][1]["content"]
    images = [
        Image.open(io.BytesIO(base64.b64decode(part["image_url"]["url"].split(",", 1)[1])))
        for part in content
        if part["type"] == "image_url"
    ]
    return images, [part["text"] for part in content if part["type"] == "text"]


def gradient(width: int, height: int) -> np.ndarray:
    """(height, width, 3) uint8 smooth picture: JPEG keeps it, sizes can be told apart."""
    x = np.linspace(0, 255, width, dtype=np.float32)[None, :]
    y = np.linspace(0, 255, height, dtype=np.float32)[:, None]
    return np.stack([x + 0 * y, y + 0 * x, np.full((height, width), 90.0)], -1).astype(np.uint8)


# ------------------------------------------------------------------ the size rule


@pytest.mark.parametrize(
    ("size", "detail", "expected"),
    [
        ((8000, 6000), None, (1024, 768)),  # a phone photo: 2048 x 1536, then short side 768
        ((6000, 8000), "high", (768, 1024)),  # upright
        ((4000, 1000), None, (2048, 512)),  # a panorama: only the 2048 box applies
        ((640, 480), None, (640, 480)),  # the simulator's frames stay as they are
        ((300, 200), None, (300, 200)),  # never enlarged
        ((8000, 6000), "low", (512, 384)),  # low detail is one 512 x 512 view
    ],
)
def test_images_shrink_to_what_the_model_takes_in(size, detail, expected) -> None:
    assert model_size(*size, detail) == expected


def test_shrinking_a_depth_image_keeps_a_thin_near_obstacle() -> None:
    depth = np.full((600, 800), 255, np.uint8)  # open water ...
    depth[:, 403] = 10  # ... and a rock pillar one pixel wide, 0.8 m away
    small = shrink_depth(depth, (100, 75))
    assert small.shape == (75, 100)
    assert (small[:, 50] == 10).all()  # the pillar's block is as near as the pillar
    assert (np.delete(small, 50, axis=1) == 255).all()  # nothing else came nearer


# ------------------------------------------------------------------ the command


def test_a_phone_sized_photo_is_sent_shrunk_and_the_size_is_said(
    server: FakeVLM, tmp_path: Path
) -> None:
    photo = tmp_path / "photo.jpg"
    Image.fromarray(gradient(4000, 3000)).save(photo, quality=90)
    depth = tmp_path / "depth.png"
    Image.fromarray(np.full((3000, 4000), 200, np.uint8)).save(depth)
    done = ask(server, str(photo), "--depth", str(depth), "--top", "3.0", "--bottom", "1.0")
    assert done.returncode == 0, done.stderr
    assert "resized photo.jpg and its depth image 4000x3000 -> 1024x768" in done.stdout
    (rgb, depth_sent), texts = sent(server)
    assert rgb.size == (1024, 768) and depth_sent.size == (1024, 768)
    assert depth_sent.mode == "L" and np.asarray(depth_sent).min() == 200
    # the same picture, only smaller: the left-to-right ramp is still there
    red = np.asarray(rgb.convert("RGB"))[384, :, 0].astype(int)
    assert red[0] < 10 and red[-1] > 245
    assert "Current observation: d_top = 3.00 m, d_bottom = 1.00 m. Colour, then depth:" in texts


def test_a_photo_alone_is_sent_without_a_depth_image_and_the_request_says_so(
    server: FakeVLM, tmp_path: Path
) -> None:
    photo = tmp_path / "photo.png"
    Image.fromarray(gradient(640, 480)).save(photo)
    done = ask(server, str(photo), "--top", "2.5")
    assert done.returncode == 0, done.stderr
    assert "turn left 15" in done.stdout
    images, texts = sent(server)
    assert len(images) == 1 and images[0].size == (640, 480)  # the colour image only
    current = next(t for t in texts if t.startswith("Current observation"))
    assert current.startswith("Current observation: d_top = 2.50 m, d_bottom = unknown.")
    assert (
        "No depth image is available for this observation: judge distances from the colour "
        "image and the sounder readings." in current
    )
    assert "nan" not in " ".join(texts)


def test_without_sounder_readings_the_model_is_told_to_use_the_colour_image(
    server: FakeVLM, tmp_path: Path
) -> None:
    photo = tmp_path / "photo.png"
    Image.fromarray(gradient(320, 240)).save(photo)
    assert ask(server, str(photo)).returncode == 0
    _, texts = sent(server)
    current = next(t for t in texts if t.startswith("Current observation"))
    assert "d_top = unknown, d_bottom = unknown" in current
    assert "judge distances from the colour image." in current


def test_a_photo_a_phone_stored_sideways_is_sent_upright(server: FakeVLM, tmp_path: Path) -> None:
    stored = np.zeros((300, 400, 3), np.uint8)
    stored[:, :200] = (255, 0, 0)  # the stored left half is red, the right half blue
    stored[:, 200:] = (0, 0, 255)
    photo = tmp_path / "phone.jpg"
    exif = Image.Exif()
    exif[0x0112] = 6  # EXIF orientation 6: turn 90 degrees clockwise to view
    Image.fromarray(stored).save(photo, exif=exif, quality=95)
    done = ask(server, str(photo))
    assert done.returncode == 0, done.stderr
    assert "upright" in done.stdout
    (rgb,), _ = sent(server)
    assert rgb.size == (300, 400)  # portrait, as the phone showed it
    pixels = np.asarray(rgb.convert("RGB")).astype(int)
    assert pixels[50, 150, 0] > 200 and pixels[50, 150, 2] < 60  # the top is the red side
    assert pixels[350, 150, 2] > 200 and pixels[350, 150, 0] < 60


def test_a_depth_image_of_another_size_is_refused_naming_both_sizes(
    server: FakeVLM, tmp_path: Path
) -> None:
    photo = tmp_path / "photo.jpg"
    Image.fromarray(gradient(4000, 3000)).save(photo)
    depth = tmp_path / "depth.png"
    Image.fromarray(np.full((480, 640), 200, np.uint8)).save(depth)
    done = ask(server, str(photo), "--depth", str(depth))
    assert done.returncode == 2
    assert done.stderr.startswith("error:") and "Traceback" not in done.stderr
    assert "640x480" in done.stderr and "4000x3000" in done.stderr
    assert server.requests == []  # refused before anything was sent


def test_a_sixteen_bit_depth_image_is_refused_rather_than_read_as_white(
    server: FakeVLM, tmp_path: Path
) -> None:
    photo = tmp_path / "photo.png"
    Image.fromarray(gradient(64, 48)).save(photo)
    depth = tmp_path / "depth_mm.png"
    Image.fromarray(np.full((48, 64), 1500, np.uint16)).save(depth)  # 1.5 m in millimetres
    done = ask(server, str(photo), "--depth", str(depth))
    assert done.returncode == 2
    assert "8-bit" in done.stderr
    assert server.requests == []


def test_a_negative_sounder_reading_is_refused(server: FakeVLM, tmp_path: Path) -> None:
    photo = tmp_path / "photo.png"
    Image.fromarray(gradient(64, 48)).save(photo)
    done = ask(server, str(photo), "--top", "-1")
    assert done.returncode == 2
    assert "d_top = -1.0 m" in done.stderr
    assert server.requests == []


@pytest.mark.parametrize("as_depth", [False, True])
def test_a_truncated_or_gigantic_image_is_one_line_and_nothing_is_sent(
    server: FakeVLM, tmp_path: Path, as_depth: bool
) -> None:
    photo = tmp_path / "photo.png"
    Image.fromarray(gradient(64, 48)).save(photo)
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(photo.read_bytes()[:60])  # OSError from getexif, uncaught
    gigantic = tmp_path / "gigantic.png"
    Image.new("1", (20_000, 20_000)).save(gigantic)  # 48 kB; DecompressionBombError
    for bad, says in [(truncated, "image file is truncated"),
                      (gigantic, "beyond Pillow's guard against decompression bombs")]:  # fmt: skip
        done = ask(server, *((str(photo), "--depth", str(bad)) if as_depth else (str(bad),)))
        assert done.returncode == 2, done.stderr
        assert done.stderr.startswith(f"error: cannot read image {bad}: ")
        assert says in done.stderr and done.stderr.count("\n") == 1
    assert server.requests == []
