"""The command line: flags -> configuration -> library calls, nothing else.

cavenav run S4                         fly S4 with the geometric pilot
cavenav run examples/osrf_cave_L.toml  fly a user mesh described by a scenario file
cavenav scenarios                      list what can be flown
"""

from __future__ import annotations

import sys
from dataclasses import replace
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cavenav.errors import CavenavError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.",
)
console = Console()
errors = Console(stderr=True, soft_wrap=True)

PILOTS = ("geometric",)


class Sounder(StrEnum):
    """Echo-sounder models (see `cavenav.sensors.rig.SensorConfig`)."""

    camera = "camera"
    beam = "beam"


@app.command()
def run(
    scenario: Annotated[str, typer.Argument(help="S1..S5, or the path of a scenario .toml file")],
    pilot: Annotated[str, typer.Option(help=f"pilot to fly: {', '.join(PILOTS)}")] = "geometric",
    seed: Annotated[int, typer.Option(help="seed of the procedural cave (S1..S5)")] = 0,
    out: Annotated[Path, typer.Option(help="folder that receives the run folder")] = Path("runs"),
    steps: Annotated[int, typer.Option(min=1, help="step budget")] = 150,
    frames: Annotated[bool, typer.Option(help="save RGB, depth PNG and EXR of every step")] = True,
    sounder: Annotated[Sounder, typer.Option(help="echo-sounder model")] = Sounder.camera,
    depth_max: Annotated[float, typer.Option(help="D_max of the depth PNG, metres")] = 20.0,
) -> None:
    """Fly one episode and write its run folder (summary, steps, frames, plots)."""
    from cavenav.episode.loop import EpisodeConfig, run_episode
    from cavenav.episode.run_folder import new_run_dir
    from cavenav.sensors.rig import SensorConfig
    from cavenav.world.scenarios import load_scenario

    if pilot not in PILOTS:
        raise CavenavError(f"unknown pilot '{pilot}'; choose one of {', '.join(PILOTS)}")
    with console.status(f"building {scenario} (seed {seed})"):
        cave = load_scenario(scenario, seed)
    config = EpisodeConfig(
        max_steps=steps,
        save_frames=frames,
        sensors=replace(SensorConfig(), sounder=sounder.value, depth_max_m=depth_max),
    )
    run_dir = new_run_dir(out, cave.name, pilot, cave.seed)
    console.print(
        f"[bold]{cave.name}[/]: {cave.description or cave.mesh.name} "
        f"({cave.mesh.triangle_count:,} triangles)"
    )
    with Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        console=console,
    ) as progress:
        task = progress.add_task(f"flying {cave.name}", total=steps, status="")

        def on_step(record: dict) -> None:
            status = f"clearance {record['clearance_m']:.2f} m  {record.get('action') or ''}"
            progress.update(task, advance=1, status=status[:60])

        try:
            result = run_episode(cave, _make_pilot(pilot), config, run_dir, on_step)
        except KeyboardInterrupt:
            progress.stop()
            errors.print(f"interrupted: the partial record is in {run_dir}")
            raise typer.Exit(130) from None
    _print_summary(result.summary)
    # soft_wrap: paths stay on one line, whatever the terminal width, for copy and paste.
    console.print(f"run folder: [bold]{run_dir}[/]", soft_wrap=True)
    for name in result.summary.get("plots", {}).values():
        console.print(f"plot:       {run_dir / name}", soft_wrap=True)


def _make_pilot(name: str):  # noqa: ANN202 - Pilot protocol
    from cavenav.pilots.geometric import GeometricPilot

    return GeometricPilot()


def _print_summary(summary: dict) -> None:
    table = Table(title="episode summary", show_header=False)
    table.add_column(style="bold")
    table.add_column()
    rows = [
        ("scenario", summary["scenario"]),
        ("pilot", summary["pilot"]),
        ("seed", summary["seed"]),
        ("termination", summary["termination"]),
        ("success", "yes" if summary["success"] else "no"),
        ("steps", summary["steps"]),
        ("collisions", summary["collisions"]),
        ("path length", f"{summary['path_length_m']:.1f} m"),
        ("min clearance", _metres(summary["min_clearance_m"])),
        ("mean clearance", _metres(summary["mean_clearance_m"])),
        ("steps below standoff", summary["steps_below_standoff"]),
        ("sensing per step", f"{summary['mean_sense_ms']} ms"),
        ("pilot per step", f"{summary['mean_pilot_ms']} ms"),
    ]
    if summary.get("failure"):
        rows.append(("failure", summary["failure"]))
    for key, value in rows:
        table.add_row(key, "-" if value is None else str(value))
    console.print(table)


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} m"


@app.command()
def scenarios(
    examples: Annotated[Path, typer.Option(help="folder searched for scenario files")] = Path(
        "examples"
    ),
) -> None:
    """List the built-in scenarios and the scenario files found in EXAMPLES."""
    from cavenav.world.scenarios import SCENARIOS

    table = Table(title="scenarios")
    table.add_column("name", style="bold", no_wrap=True)
    table.add_column("kind")
    table.add_column("description")
    for name, factory in SCENARIOS.items():
        table.add_row(name, "procedural (--seed)", factory.summary)
    for path in sorted(examples.glob("*.toml")) if examples.is_dir() else []:
        table.add_row(str(path), "scenario file", _first_comment(path))
    console.print(table)


def _first_comment(path: Path) -> str:
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("#"):
            return line.lstrip("# ").strip()
    return ""


def main() -> None:
    """Entry point: typer reports usage errors; our own errors become one line, exit 2."""
    try:
        app()
    except CavenavError as exc:
        errors.print(f"[red]error:[/] {exc}", highlight=False)
        sys.exit(2)
    except KeyboardInterrupt:
        errors.print("interrupted")
        sys.exit(130)


if __name__ == "__main__":
    main()
