"""Depth in metres from the colour image alone: a monocular depth model, for a vehicle
that carries no depth camera (a BlueROV2 as sold has none).

The model runs through transformers' ``depth-estimation`` pipeline, so any model that
pipeline takes will do, but the method needs metres: a *metric* model (Depth Anything
V2 Metric, ZoeDepth, DPT trained on metric data). A model whose configuration says it
predicts relative depth is refused, because relative inverse depth read as metres puts
the far wall next to the lens. cavenav downloads nothing: the model is a local folder
(``save_pretrained`` of one fetched beforehand).

What it estimates is no measurement: the run folder names the model, and pilots judge
the estimate as a depth image like any other. The shield then guards against what the
model believes, not what is there.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from cavenav.core.errors import ConfigError, DependencyError

__all__ = ["MonocularDepth"]

INSTALL_HINT = "a monocular depth model runs on transformers: pip install -e '.[transformers]'"


# Models whose configuration says nothing of their kind (DPT, GLPN, ZoeDepth) are as likely
# relative (MiDaS) as metric: only these are taken without being told (`METRIC_TYPES`).
METRIC_TYPES = ("zoedepth", "glpn", "depth_pro")


def _check_metric(config: Any, model: str | Path) -> None:  # noqa: ANN401 - a transformers config
    """Refuse a model that is not known to predict metres.

    Raises:
        ConfigError: a relative model, or one whose kind its configuration does not say.
    """
    kind = getattr(config, "depth_estimation_type", None)
    if kind == "metric" or (kind is None and config.model_type in METRIC_TYPES):
        return
    said = (
        "it predicts relative depth"
        if kind == "relative"
        else (f"its configuration ({config.model_type}) does not say it predicts metres")
    )
    raise ConfigError(
        f"depth model {model}: {said}, and the pilots need metres: give a metric model "
        "(Depth Anything V2 Metric, ZoeDepth, GLPN, Depth Pro)"
    )


class MonocularDepth:
    """A transformers depth-estimation model that gives metres for an RGB image."""

    def __init__(self, model: str | Path, device: str = "auto"):
        """Load the model in the folder ``model`` on ``device`` ("auto": CUDA when there
        is one, else the CPU).

        Raises:
            ConfigError: no such folder, or a model that predicts relative depth.
            DependencyError: transformers or torch is not installed.
        """
        folder = Path(model)
        if not (folder / "config.json").is_file():
            raise ConfigError(
                f"depth model {model}: not a folder holding a model (config.json); give the "
                "folder a metric depth model was saved to (cavenav downloads nothing)"
            )
        try:
            import torch
            from transformers import AutoConfig, pipeline
        except ImportError:
            raise DependencyError(INSTALL_HINT) from None
        try:
            config = AutoConfig.from_pretrained(folder)
            _check_metric(config, model)
            if device == "auto":
                device = "cuda" if torch.cuda.is_available() else "cpu"
            self._pipeline: Any = pipeline("depth-estimation", model=str(folder), device=device)
        except (OSError, ValueError, KeyError, RuntimeError) as exc:  # a broken or odd model
            raise ConfigError(f"depth model {model}: cannot load it: {exc}") from None
        self.name, self.device = folder.name, device

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """Planar depth in metres, (H, W) float32 like ``rgb``; NaN where the model gave
        no positive finite value."""
        from PIL import Image

        predicted = self._pipeline(Image.fromarray(rgb))["predicted_depth"]
        depth = np.asarray(predicted.float().cpu().numpy(), np.float32).squeeze()
        if depth.shape != rgb.shape[:2]:  # a pipeline that did not resize it back
            depth = np.asarray(
                Image.fromarray(depth).resize(rgb.shape[1::-1], Image.Resampling.BILINEAR),
                np.float32,
            )
        depth[~(np.isfinite(depth) & (depth > 0))] = math.nan
        return depth
