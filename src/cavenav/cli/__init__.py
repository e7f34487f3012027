"""The command line: flags -> configuration -> library calls, nothing else.

cavenav run S4                         fly S4 with the geometric pilot
cavenav run examples/osrf_cave_L.toml  fly a user mesh described by a scenario file
cavenav render S4 --water turbid       contact sheet of the views along the passage
cavenav scenarios                      list what can be flown
cavenav eval --seeds 0-19 --out DIR    families x 20 caves each, resumable, with a report
cavenav compare DIR_A DIR_B            two sweeps paired by cave (McNemar)
cavenav report DIR                     the HTML report of a sweep or a run folder
cavenav video RUN                      an MP4 of one episode
cavenav fly --sim S4 --yes             the same pilots on an ArduSub vehicle over MAVLink
cavenav fake-sub                       a simulated ArduSub autopilot to fly against
cavenav dataset SWEEP --out DIR        flights as training data for a VLM (Hugging Face)
cavenav finetune DATA --new small      train a VLM pilot on it (or --base MODEL_DIR)

Each command is written, with its options, in the module of its kind: `episodes` (run,
render, ask, view, video, scenarios, warmup), `sweeps` (eval, compare, report), `vehicle`
(fly, fake-sub) and `training` (dataset, finetune); this module only names them. The
options several commands share are declared once: the VLM pilot's and the episode's in
`episode_flags`, the live view's and a vehicle's in `vehicle_flags`, by the machinery in
`flags`. `flights` flies with a progress bar and handles Ctrl-C; `output` prints tables.
"""

from __future__ import annotations

import errno
import sys
import warnings
from typing import Any

import typer
from rich.markup import escape

from cavenav.cli.episodes import ask, render, run, scenarios, video, view, warmup
from cavenav.cli.fake_sub import fake_sub
from cavenav.cli.output import errors
from cavenav.cli.sweeps import FramesMode, compare, eval_, report
from cavenav.cli.training import dataset, finetune
from cavenav.cli.vehicle import fly
from cavenav.core.errors import CavenavError
from cavenav.core.redaction import redact

__all__ = ["FramesMode", "app", "main"]

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="cavenav: VLM-steered navigation of an underwater vehicle through unseen caves.",
)
# In the order `cavenav --help` lists them.
app.command()(dataset)
app.command()(finetune)
app.command()(run)
app.command()(render)
app.command()(ask)
app.command("eval")(eval_)
app.command()(compare)
app.command()(view)
app.command()(report)
app.command()(video)
app.command()(fly)
app.command("fake-sub")(fake_sub)
app.command()(warmup)
app.command()(scenarios)


def main() -> None:
    """Entry point; the exit status is part of the interface (docs/guides/faults.md).

    0: the command did its work (an episode ended at the exit, a wall or the budget).
    1: an episode ended as a pilot failure, or the run folder could not be written.
    2: bad input (a typer usage error, or a `CavenavError`), refused before anything
       was written.
    3: `fly`: the vehicle failed the bridge (no heartbeat, refused, a stale link).
    130: interrupted (Ctrl-C); what was recorded so far stays valid.
    143: `eval` stopped by SIGTERM, as by Ctrl-C.
    """
    warnings.showwarning = _show_warning
    try:
        app()
    except CavenavError as exc:
        # One line, even when the message quotes a model's multi-line reply; no key in it,
        # whatever a server echoed (backends redact already: this is the last guard).
        message = redact(" ".join(str(exc).split()))
        errors.print(f"[red]error:[/] {escape(message)}", highlight=False)
        sys.exit(exc.exit_status)
    except KeyboardInterrupt:
        errors.print("interrupted")
        sys.exit(130)
    except OSError as exc:
        if exc.errno != errno.ENAMETOOLONG:
            raise
        # A path given (--out, a scenario file) that no file system takes: bad input,
        # met where the path is first looked at, before anything is written.
        name = str(exc.filename or "")
        shown = name if len(name) <= 80 else f"{name[:40]}...{name[-37:]}"
        errors.print(f"error: a path is too long for the file system: {escape(shown)}")
        sys.exit(2)


def _show_warning(message: Warning | str, category: type[Warning], *_: Any, **__: Any) -> None:
    """Our warnings (a mesh in centimetres, ...) as one line; others as Python prints them."""
    from cavenav.core.errors import CavenavWarning

    if issubclass(category, CavenavWarning):
        errors.print(f"[yellow]warning:[/] {escape(str(message))}", highlight=False)
    else:
        errors.print(f"{category.__name__}: {escape(str(message))}", highlight=False)
