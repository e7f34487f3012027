"""Build a tiny, randomly initialised Idefics3 vision-language model on disk.

Two layers of hidden size 32 for both the vision and the text tower, a byte-level BPE
tokenizer trained here on a few sentences plus the Idefics3 special tokens, and an image
processor that shrinks every image to 64 px (`cavenav.training.small_vlm`, at a tenth of
the small model's size): about 0.4 MB, loaded in a fraction of a second. Nothing is
downloaded. Its replies are garbage by construction, which is exactly what the failure
path must survive.
"""

from __future__ import annotations

from pathlib import Path

from cavenav.training.small_vlm import SmallVLM, build_small_vlm

TINY = SmallVLM(hidden=32, layers=2, heads=2, image_px=64, vocab=320)  # 4 tokens an image


def build_tiny_idefics3(folder: Path) -> Path:
    sentences = ["forward 0.5 m, turn left 15 deg", "the passage continues ahead", "hold"] * 20
    return build_small_vlm(folder, sentences, TINY)
