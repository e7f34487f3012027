"""Images as a model's request carries them: encoded once, in the format and size asked.

A VLM step re-sends its K earlier observations, and the run folder then names which of
the stored images are the current observation's. Both read the data URL made the first
time an image array was encoded (`data_url`, `sent_as`) rather than encoding it again:
at 640x480 a colour PNG costs Pillow about 17 ms.

The default, PNG at the camera's size, makes the very bytes earlier versions sent, so
reply caches (`--cache`, keyed by the request's content) stay valid. JPEG at a chosen
quality and a smaller size are settings (`--image-format`, `--jpeg-quality`,
`--image-size`): a hosted model bills an image by its size, and a server decodes a JPEG
faster. The depth image always travels as PNG (its 8 bits are distances that lossy
coding would move), resized with the colour image.
"""

from __future__ import annotations

import base64
import io
import threading
import weakref
from dataclasses import dataclass
from typing import Literal

import numpy as np
from PIL import Image

from cavenav.core.errors import ConfigError

__all__ = [
    "IMAGE_FORMATS",
    "ImageEncoding",
    "data_url",
    "drawing_on",
    "remember_drawing",
    "sent_as",
]

IMAGE_FORMATS = ("png", "jpeg")


@dataclass(frozen=True)
class ImageEncoding:
    """How an observation's images travel in a request.

    Attributes:
        colour: "png" (lossless, the default) or "jpeg" (simplejpeg, 4:2:0 chroma).
        quality: the JPEG quality, 1-100.
        size: (width, height) to resize both images to, by area averaging (Pillow's box
            filter); None sends them as the camera made them.
    """

    colour: Literal["png", "jpeg"] = "png"
    quality: int = 90
    size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.colour not in IMAGE_FORMATS:
            raise ConfigError(
                f"--image-format must be one of {', '.join(IMAGE_FORMATS)}, not '{self.colour}'"
            )
        if not 1 <= self.quality <= 100:
            raise ConfigError(f"--jpeg-quality must lie in 1-100, not {self.quality}")


PNG = ImageEncoding()
# The data URL each live image array was last sent as, by id: the entry goes when the
# array does (a weak reference's callback), before its id can be given to another.
_SENT: dict[int, tuple[weakref.ref, ImageEncoding, str]] = {}
_LOCK = threading.Lock()
# The copy with choices drawn on it that a designed pilot sent in place of a colour image
# (`cavenav.pilots.designs`), by the id of the colour image it was drawn on, while it lives.
_DRAWN: dict[int, tuple[weakref.ref, np.ndarray]] = {}


def data_url(image: np.ndarray, encoding: ImageEncoding = PNG) -> str:
    """An (H, W) grey or (H, W, 3) colour uint8 image as a data URL, encoded as
    ``encoding`` asks the first time this array is asked for, then read back.

    The array must not change after it is sent (observations never do).
    """
    key = id(image)
    with _LOCK:
        known = _SENT.get(key)
    if known is not None and known[0]() is image and known[1] == encoding:
        return known[2]
    url = _encode(image, encoding)

    def forget(ref: weakref.ref) -> None:
        with _LOCK:
            if key in _SENT and _SENT[key][0] is ref:
                del _SENT[key]

    with _LOCK:
        _SENT[key] = (weakref.ref(image, forget), encoding, url)
    return url


def sent_as(image: np.ndarray) -> str | None:
    """The data URL ``image`` was sent as (`data_url`), or None if it never was."""
    with _LOCK:
        known = _SENT.get(id(image))
    return known[2] if known is not None and known[0]() is image else None


def remember_drawing(image: np.ndarray, drawn: np.ndarray) -> None:
    """Say that ``drawn``, a copy of the colour image ``image`` with choices drawn on it,
    was sent in its place: the run folder then stores which image the model saw."""
    key = id(image)

    def forget(ref: weakref.ref) -> None:
        with _LOCK:
            gone = _DRAWN.pop(key) if key in _DRAWN and _DRAWN[key][0] is ref else None
        # The drawn copy goes here, outside the lock: its own entry in `_SENT` goes with it.
        del gone

    with _LOCK:
        replaced = _DRAWN.get(key)
        _DRAWN[key] = (weakref.ref(image, forget), drawn)
    del replaced


def drawing_on(image: np.ndarray) -> np.ndarray | None:
    """The drawn copy sent in place of ``image`` (`remember_drawing`), if one was."""
    with _LOCK:
        known = _DRAWN.get(id(image))
    return known[1] if known is not None and known[0]() is image else None


def _encode(image: np.ndarray, encoding: ImageEncoding) -> str:
    picture = Image.fromarray(image)
    if encoding.size is not None and picture.size != encoding.size:
        picture = picture.resize(encoding.size, Image.Resampling.BOX)
    if encoding.colour == "jpeg" and picture.mode == "RGB":
        import simplejpeg

        pixels = np.ascontiguousarray(np.asarray(picture))
        data = simplejpeg.encode_jpeg(pixels, encoding.quality, "RGB", "420")
        return "data:image/jpeg;base64," + base64.b64encode(data).decode("ascii")
    buffer = io.BytesIO()
    picture.save(buffer, format="PNG", compress_level=1)  # the bytes reply caches know
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")
