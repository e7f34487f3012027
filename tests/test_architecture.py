"""Imports flow one way: types <- world <- sensors <- shield <- pilots <- env <- episode <-
evaluation <- cli."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "cavenav"


def imports_of(path: Path) -> set[str]:
    """Every cavenav module a file imports, at the top or inside a function."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("cavenav"):
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("cavenav")}
    return found


def modules(folder: str) -> list[Path]:
    return sorted((SRC / folder).glob("*.py")) if (SRC / folder).is_dir() else [SRC / folder]


TOP = ("cavenav.evaluation", "cavenav.cli")  # nothing below them imports these


@pytest.mark.parametrize(
    ("layer", "forbidden"),
    [
        ("types.py", ("cavenav.",)),
        ("world", ("cavenav.sensors", "cavenav.pilots", "cavenav.env", "cavenav.episode", *TOP)),
        ("sensors", ("cavenav.pilots", "cavenav.env", "cavenav.episode", "cavenav.shield", *TOP)),
        ("shield.py", ("cavenav.world", "cavenav.pilots", "cavenav.env", "cavenav.episode", *TOP)),
        ("pilots", ("cavenav.world", "cavenav.env", "cavenav.episode", "cavenav.wrappers", *TOP)),
        ("env.py", ("cavenav.pilots", "cavenav.episode", *TOP)),
        ("episode", TOP),
        ("evaluation", ("cavenav.cli",)),
    ],
)
def test_a_layer_never_imports_the_layers_above_it(layer: str, forbidden: tuple[str, ...]) -> None:
    for path in modules(layer):
        bad = {m for m in imports_of(path) if m.startswith(forbidden)}
        assert not bad, f"{path.name} imports {bad}"


def test_the_loop_and_the_plots_do_not_import_each_other() -> None:
    assert "cavenav.episode.plots" not in imports_of(SRC / "episode" / "loop.py")
    assert "cavenav.episode.loop" not in imports_of(SRC / "episode" / "plots.py")


def test_the_episode_layer_never_takes_apart_backend_objects() -> None:
    for path in modules("episode"):
        assert "cavenav.pilots.backends" not in imports_of(path), path.name
        assert ".completion" not in path.read_text(), path.name
