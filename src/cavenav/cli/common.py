"""What the commands share: their common arguments and the first steps of a flight."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated, Any

import typer

from cavenav.cli.output import console
from cavenav.cli.vehicle_flags import LiveView
from cavenav.core.errors import CavenavError
from cavenav.episode.settings import EpisodeConfig
from cavenav.pilots.factory import PilotSpec, VLMOptions

__all__ = [
    "FramesOpt",
    "FromOpt",
    "PilotOpt",
    "PolicyOpt",
    "RunsOut",
    "ScenarioArg",
    "TeacherOpt",
    "built",
    "camera_for",
    "check_view",
    "pilot_spec",
]

ScenarioArg = Annotated[
    str, typer.Argument(help="a family (S1..S5, crawl, maze, long) or a scenario .toml file")
]
PilotOpt = Annotated[str, typer.Option(help="pilot to fly: geometric, vlm, replay, random, policy")]
RunsOut = Annotated[Path, typer.Option(help="folder that receives the run folder")]
FramesOpt = Annotated[bool, typer.Option(help="save RGB, depth PNG and EXR of every step")]
FromOpt = Annotated[Path | None, typer.Option("--from", help="run folder to replay")]
PolicyOpt = Annotated[
    Path | None,
    typer.Option(
        help="model file the policy pilot flies (Stable-Baselines3 .zip; --resolution follows it)"
    ),
]
TeacherOpt = Annotated[
    str | None,
    typer.Option(
        help="a pilot (geometric, random) that decides alongside at every step, recorded "
        "as the step's teacher label for `cavenav dataset --labels teacher` (DAgger)"
    ),
]


def check_view(view: LiveView) -> None:
    """A Rerun recording's file checked first, before a pilot, a cave or a vehicle."""
    if view.rerun_save:
        from cavenav.episode.rerun_log import check_recording_path

        check_recording_path(Path(view.rerun_save))


def built(settings: EpisodeConfig, scenario: str, seed: int) -> Any:  # noqa: ANN401
    """The cave ``scenario`` of ``seed``, built under a status line (a large mesh takes a
    while)."""
    with console.status(f"building {scenario} (seed {seed})"):
        return settings.load(scenario, seed)


def pilot_spec(
    pilot: str,
    vlm: VLMOptions,
    from_: Path | None,
    policy: Path | None,
    teacher: str | None = None,
) -> PilotSpec:
    return PilotSpec(
        pilot,
        vlm.for_model(),  # a model folder cavenav finetune wrote: asked as it learned
        recording=str(from_) if from_ else None,
        policy=str(policy.absolute()) if policy else None,  # as workers elsewhere find it
        teacher=teacher,
    )


def camera_for(spec: PilotSpec, settings: EpisodeConfig) -> EpisodeConfig:
    """``settings`` with the camera size a pilot trained at one size needs (a policy):
    set when --resolution was not given, refused when it names another size."""
    size = spec.image_size()
    if size is None or settings.resolution == size:
        return settings
    if settings.resolution is not None:
        given, wanted = (f"{w}x{h}" for w, h in (settings.resolution, size))
        raise CavenavError(
            f"--resolution {given}: the policy {spec.policy} was trained on {wanted} images; "
            f"leave --resolution out or give {wanted}"
        )
    console.print(f"[yellow]note:[/] the camera is {size[0]}x{size[1]}, as the policy saw it")
    return replace(settings, resolution=size)
