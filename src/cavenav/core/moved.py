"""The modules that moved into the layers, still importable by their old names for one
release, with a `DeprecationWarning`: ``import cavenav.env`` gives `cavenav.sim.env`.

The old names are aliases, not copies: ``cavenav.env is cavenav.sim.env``, so a patch or
an ``isinstance`` through either name sees the same objects.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import ModuleType

__all__ = ["MOVED", "install"]

# Each module's old name and where it lives now (moved in version 0.1.0, after November 2026).
MOVED = {
    f"cavenav.{name}": f"cavenav.{layer}.{name}"
    for layer, names in {
        "core": ("types", "errors", "files", "redaction"),
        "motion": ("actions", "kinematics", "energy"),
        "safety": ("reckoning", "shield", "cave_map", "headway"),
        "sim": ("env", "vector_env", "wrappers", "cave_sensors"),
    }.items()
    for name in names
}


class _OldNames(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds a moved module by its old name and hands over the module under its new one."""

    def find_spec(
        self, name: str, path: object = None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        return importlib.machinery.ModuleSpec(name, self) if name in MOVED else None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warnings.warn(
            f"{spec.name} is now {MOVED[spec.name]}; the old name goes in a later release",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(MOVED[spec.name])

    def exec_module(self, module: ModuleType) -> None:
        """The module ran when it was imported by its new name."""


def install() -> None:
    """Let the old names import (once per process)."""
    if not any(isinstance(finder, _OldNames) for finder in sys.meta_path):
        sys.meta_path.append(_OldNames())
