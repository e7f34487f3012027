"""The package's folders are its layers, and imports flow one way, up from the bottom:

    core (types, errors, files)  <-  motion (actions, kinematics, energy)  <-  world
    <-  sensors  <-  safety (shield, reckoning, cave map, headway)  <-  pilots  <-  sim
    (the Gymnasium environments)  <-  episode  <-  evaluation  <-  training  <-  cli

`vehicle` (the MAVLink bridge and its fake) knows only core and motion: the environment
takes it as a `Motion` without importing it, and only `sim.cave_sensors`, which serves a
cave's images to a fake vehicle, imports it. No module sits loose at the top of the package
but its entry point, `cavenav/__init__.py`."""

from __future__ import annotations

import ast
import sys
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


# What each layer may import besides itself and the package's root (`cavenav.__version__`).
BELOW = {
    "core": (),
    "motion": ("core",),
    "vehicle": ("core", "motion"),
    "world": ("core", "motion"),
    "sensors": ("core", "motion", "world"),
    "safety": ("core", "motion", "sensors"),  # never the cave model: a vehicle has none
    "pilots": ("core", "motion", "sensors", "safety"),  # nor the pilots: they sense it
    "sim": ("core", "motion", "world", "sensors", "safety", "vehicle"),
    "episode": ("core", "motion", "world", "sensors", "safety", "pilots", "sim"),
    "evaluation": ("core", "motion", "world", "sensors", "safety", "pilots", "sim", "episode"),
}
BELOW["training"] = (*BELOW["evaluation"], "evaluation")
BELOW["cli"] = (*BELOW["training"], "training", "vehicle")


@pytest.mark.parametrize("layer", sorted(BELOW))
def test_a_layer_imports_only_the_layers_below_it(layer: str) -> None:
    allowed = {"cavenav", "cavenav.__version__", "cavenav.SCENARIO_SET"}
    prefixes = tuple(f"cavenav.{name}" for name in (layer, *BELOW[layer]))
    for path in modules(layer):
        bad = {m for m in imports_of(path) - allowed if not m.startswith(prefixes)}
        assert not bad, f"{path.relative_to(SRC)} imports {bad}"


def test_every_module_sits_in_a_layer() -> None:
    loose = sorted(path.name for path in SRC.glob("*.py") if path.name != "__init__.py")
    assert not loose, f"modules outside the layers: {loose}"
    folders = {path.name for path in SRC.iterdir() if (path / "__init__.py").is_file()}
    assert folders == set(BELOW), "a layer the import rules do not know"


def test_the_environments_never_import_the_vehicle() -> None:
    for name in ("env.py", "vector_env.py", "wrappers.py"):
        bad = {m for m in imports_of(SRC / "sim" / name) if m.startswith("cavenav.vehicle")}
        assert not bad, f"sim/{name} imports {bad}"


def test_old_module_names_still_import_with_a_warning() -> None:
    import importlib

    from cavenav.core.moved import MOVED

    assert all((SRC / (new.split(".", 1)[1].replace(".", "/") + ".py")).is_file()
               for new in MOVED.values())  # fmt: skip
    for old, new in MOVED.items():
        sys.modules.pop(old, None)
        with pytest.warns(DeprecationWarning, match=f"{old} is now {new}"):
            assert importlib.import_module(old) is importlib.import_module(new)


def body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A function's lines from its first statement after the docstring to its end: what
    it does, not the parameters it declares (a command lists every option it takes)."""
    body = node.body
    if len(body) > 1 and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]
    return node.end_lineno - body[0].lineno + 1


def test_no_function_outside_the_numba_kernels_is_longer_than_60_lines() -> None:
    """A longer function is asking to be split; the kernels are one loop over pixels each,
    kept whole so that numba compiles them to one (complexity: ruff's C901, at 15)."""
    long = []
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "kernels.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = body_lines(node)
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


def test_the_tests_mirror_the_layers() -> None:
    tests = Path(__file__).resolve().parent
    folders = {path.name for path in tests.iterdir() if (path / "__init__.py").is_file()}
    assert folders <= set(BELOW), f"test folders that name no layer: {folders - set(BELOW)}"
    loose = sorted(path.name for path in tests.glob("test_*.py"))
    assert loose == ["test_architecture.py"], f"tests outside the layers' folders: {loose}"
