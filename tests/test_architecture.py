"""Imports flow one way: types <- world <- sensors <- reckoning <- shield, cave_map <- pilots
<- env <- episode <- evaluation <- training <- cli; `headway` (what "stuck" means) sits below env;
`files` (how every layer writes a file in place) is a leaf like types, and `energy` (what
moves cost a BlueROV2) knows only types and errors;
`vehicle` (the MAVLink bridge) knows only types, actions and kinematics: the environment
takes it as a `Motion` without importing it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "cavenav"


def imports_of(path: Path) -> set[str]:
    """Every cavenav module a file imports, at the top or inside a function, relative
    imports resolved; ``from cavenav.x import y`` counts ``cavenav.x`` and ``cavenav.x.y``
    (y may be a module)."""
    package = ["cavenav", *path.relative_to(SRC).parent.parts]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            if module.startswith("cavenav"):
                found |= {module} | {f"{module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("cavenav")}
    return found


def modules(folder: str) -> list[Path]:
    """The layer's source files, subpackages included; a layer that is gone is an error."""
    found = sorted((SRC / folder).rglob("*.py")) if (SRC / folder).is_dir() else [SRC / folder]
    assert found and all(path.is_file() for path in found), f"no layer {folder} in {SRC}"
    return found


TOP = ("cavenav.evaluation", "cavenav.training", "cavenav.cli")  # nothing below them imports these


@pytest.mark.parametrize(
    ("layer", "forbidden"),
    [
        ("types.py", ("cavenav.",)),
        ("files.py", ("cavenav.",)),
        ("world", ("cavenav.sensors", "cavenav.pilots", "cavenav.env", "cavenav.episode", *TOP)),
        ("sensors", ("cavenav.pilots", "cavenav.env", "cavenav.episode", "cavenav.shield", *TOP)),
        (
            "reckoning.py",
            (
                "cavenav.world",
                "cavenav.shield",
                "cavenav.cave_map",
                "cavenav.pilots",
                "cavenav.env",
                "cavenav.episode",
                *TOP,
            ),
        ),
        (
            "energy.py",
            (
                "cavenav.world",
                "cavenav.sensors",
                "cavenav.pilots",
                "cavenav.env",
                "cavenav.episode",
                *TOP,
            ),
        ),
        (
            "headway.py",
            ("cavenav.pilots", "cavenav.env", "cavenav.episode", "cavenav.wrappers", *TOP),
        ),
        ("shield.py", ("cavenav.world", "cavenav.pilots", "cavenav.env", "cavenav.episode", *TOP)),
        (
            "cave_map.py",
            ("cavenav.world", "cavenav.pilots", "cavenav.env", "cavenav.episode", *TOP),
        ),
        ("pilots", ("cavenav.world", "cavenav.env", "cavenav.episode", "cavenav.wrappers", *TOP)),
        ("env.py", ("cavenav.pilots", "cavenav.episode", "cavenav.vehicle", *TOP)),
        ("episode", ("cavenav.vehicle", *TOP)),
        ("evaluation", ("cavenav.training", "cavenav.cli")),
        ("training", ("cavenav.cli",)),
        (
            "vehicle",
            (
                "cavenav.world",
                "cavenav.sensors",
                "cavenav.shield",
                "cavenav.pilots",
                "cavenav.env",
                "cavenav.episode",
                "cavenav.wrappers",
                *TOP,
            ),
        ),
    ],
)
def test_a_layer_never_imports_the_layers_above_it(layer: str, forbidden: tuple[str, ...]) -> None:
    for path in modules(layer):
        bad = {m for m in imports_of(path) if m.startswith(forbidden)}
        assert not bad, f"{path.name} imports {bad}"


def test_no_function_outside_the_numba_kernels_is_longer_than_60_lines() -> None:
    """A longer function is asking to be split; the kernels are one loop over pixels each,
    kept whole so that numba compiles them to one (complexity: ruff's C901, at 15)."""
    long = []
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "kernels.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > 60:
                    long.append(f"{path.relative_to(SRC)}:{node.lineno} {node.name} ({lines})")
    assert not long, f"functions over 60 lines: {long}"


def test_the_loop_and_the_plots_do_not_import_each_other() -> None:
    assert "cavenav.episode.plots" not in imports_of(SRC / "episode" / "loop.py")
    assert "cavenav.episode.loop" not in imports_of(SRC / "episode" / "plots.py")


def test_the_episode_layer_never_takes_apart_backend_objects() -> None:
    for path in modules("episode"):
        assert "cavenav.pilots.backends" not in imports_of(path), path.name
        assert ".completion" not in path.read_text(), path.name


def module_name(path: Path) -> str:
    """``src/cavenav/world/mesh.py`` -> ``cavenav.world.mesh``; a package is its ``__init__``."""
    parts = ["cavenav", *path.relative_to(SRC).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_circles() -> list[list[str]]:
    """Every group of cavenav modules that import one another, directly or by a detour
    (the strongly connected parts of the import graph), each sorted.

    Built from the source, not from what ``import`` happens to load: every import
    statement counts, at the top, inside a function or under ``if TYPE_CHECKING``. An
    import put inside a function to break a circle still makes the two modules need each
    other (each can only be understood, tested or moved with the other), and it only
    hides the circle from Python until the day someone hoists the import; a module whose
    signatures name another's type depends on it as much as one that calls it. An edge
    goes to the modules the statement names (``from cavenav.world import mesh`` and
    ``from cavenav.world.mesh import CaveMesh`` both to ``cavenav.world.mesh``), not to
    the packages above them, whose ``__init__`` files import nothing of cavenav.
    """
    names = {module_name(path): path for path in SRC.rglob("*.py")}
    graph = {name: imports_of(path) & names.keys() - {name} for name, path in names.items()}
    reach: dict[str, set[str]] = {}
    for name in graph:  # every module reachable from each, by a walk over the graph
        seen, todo = set(), [name]
        while todo:
            for other in graph[todo.pop()] - seen:
                seen.add(other)
                todo.append(other)
        reach[name] = seen
    groups = {tuple(sorted(m for m in reach[n] if n in reach[m])) for n in graph if n in reach[n]}
    return [list(group) for group in sorted(groups)]


def test_no_two_modules_import_each_other_even_by_a_detour() -> None:
    circles = import_circles()
    assert not circles, "modules that import one another: " + "; ".join(map(", ".join, circles))
