"""Files that appear whole or not at all: the one way cavenav writes a file in place.

Run folders (frames, summaries, images), the cave and lighting caches and the model
reply cache are all written to a temporary beside their name and renamed into place, so
a reader, or a process killed half-way, never finds half a file.
"""

from __future__ import annotations

import errno
import os
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "cannot_write",
    "not_a_file_to_replace",
    "probe_writable",
    "save_figure",
    "write_then_rename",
]


def write_then_rename(path: Path, write: Callable[[Path], object]) -> None:
    """``write`` into a hidden temporary beside ``path``, then rename it into place.

    Only a regular file is ever replaced: a device, a pipe or a folder at ``path`` is an
    OSError (the rename would put a file where ``/dev/full`` was). A failed write (a full
    disk, Ctrl-C) removes its temporary. The temporary is named after the writing process
    and thread, so writers filling one cache at once (a sweep's workers) never write into
    each other's. ``write`` gets the temporary's path, whose suffix is ``.tmp``: give
    libraries that add their own suffix an open file instead (or a format, as
    `save_figure` does).
    """
    if path.exists() and not path.is_file():  # a rename would put a file in its place
        raise OSError(errno.EEXIST, f"{path} is no regular file, so it is not replaced", str(path))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def save_figure(figure: Any, path: Path, **options: Any) -> None:  # noqa: ANN401 - matplotlib's
    """``figure.savefig`` to ``path`` through `write_then_rename`: a plot cut short (Ctrl-C,
    a full disk) leaves no truncated image under its name. The format is the name's."""
    path = Path(path)
    write_then_rename(path, lambda tmp: figure.savefig(tmp, format=path.suffix[1:], **options))


def not_a_file_to_replace(path: Path) -> str | None:
    """Why ``path`` cannot take a file cavenav writes, or None: it is a folder, something
    other than a regular file (a device, a pipe, a socket: `write_then_rename` never
    replaces one), or a file stands where a folder above it should."""
    path = Path(path)
    if path.is_dir():
        return f"{path} is a folder"
    if path.exists() and not path.is_file():
        return f"{path} is no regular file (a device, a pipe or a socket)"
    above = next((folder for folder in path.parents if folder.exists()), None)
    if above is not None and not above.is_dir():
        return f"{above} is a file, not a folder"
    return None


def cannot_write(path: Path) -> str | None:
    """Why a file cannot be written at ``path``, or None, found before any work and
    without creating anything: `not_a_file_to_replace`, or the nearest folder above it
    that exists cannot be written (read-only)."""
    path = Path(path).absolute()
    why = not_a_file_to_replace(path)
    if why is None:
        above = next(folder for folder in path.parents if folder.exists())
        try:
            probe_writable(above)
        except OSError as exc:
            why = f"{above}: {exc.strerror or exc}"
    return why


def probe_writable(folder: Path) -> None:
    """Make and remove an entry in ``folder``: what access() cannot tell (a read-only
    mount, root's rights, ACLs) shows as the OSError a real write would meet."""
    os.rmdir(tempfile.mkdtemp(prefix=".probe-", dir=folder))
