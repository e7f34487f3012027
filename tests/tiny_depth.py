"""Build a tiny, randomly initialised Depth Anything model on disk (about 0.3 MB).

A two-layer DINOv2 backbone of hidden size 32 and a metric head (20 m at most), with an
image processor that shrinks every image to 56 px. Nothing is downloaded; its depths are
meaningless by construction (about 10 m everywhere), which is all a test of the plumbing
needs: metres come back at the image's size.
"""

from __future__ import annotations

from pathlib import Path


def build_tiny_depth_anything(folder: Path, kind: str = "metric") -> Path:
    from transformers import (
        DepthAnythingConfig,
        DepthAnythingForDepthEstimation,
        Dinov2Config,
        DPTImageProcessor,
    )

    backbone = Dinov2Config(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=2, intermediate_size=64,
        image_size=56, patch_size=14, out_features=["stage1", "stage2"],
        reshape_hidden_states=False,
    )  # fmt: skip
    config = DepthAnythingConfig(
        backbone_config=backbone, reassemble_hidden_size=32, patch_size=14,
        neck_hidden_sizes=[16, 32], fusion_hidden_size=16, head_hidden_size=16,
        reassemble_factors=[4, 2], depth_estimation_type=kind, max_depth=20,
    )  # fmt: skip
    DepthAnythingForDepthEstimation(config).save_pretrained(folder)
    size = {"height": 56, "width": 56}
    DPTImageProcessor(size=size, keep_aspect_ratio=False, do_pad=False).save_pretrained(folder)
    return folder
