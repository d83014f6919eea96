"""The code of an earlier commit beside this tree, for benchmarks that compare the two in one
run: `git archive COMMIT` extracted into a folder, run with this interpreter and environment
(`PYTHONPATH` set to the folder, so its packages shadow this tree's). A tree from before the one
import name `archery` gets a `sitecustomize` that names its top-level packages `archery.*` too
(the same module objects), so `python -m archery.apps.cli` and a workload's `archery.*` imports
run its code, never this tree's."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

from benchmarks.machine import cpu_model

T = TypeVar("T")

__all__ = ["ROOT", "env_for", "header", "interleaved", "tree_at"]

ROOT = Path(__file__).resolve().parents[1]


#: Written into a tree from before `archery`: its packages, imported under `archery.NAME` too
ALIASES = """
import importlib, importlib.abc, importlib.machinery, importlib.util, sys, types


class _Alias(importlib.abc.Loader):
    def __init__(self, real):
        self.real = real

    def create_module(self, spec):
        if self.real is None:
            module = types.ModuleType(spec.name)
            module.__path__ = []
            return module
        return importlib.import_module(self.real)

    def exec_module(self, module):
        pass

    def get_code(self, fullname):
        return importlib.util.find_spec(self.real).loader.get_code(self.real)


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "archery":
            return importlib.machinery.ModuleSpec(name, _Alias(None), is_package=True)
        if not name.startswith("archery."):
            return None
        real = name[len("archery."):]
        found = importlib.util.find_spec(real)
        if found is None:
            return None
        package = found.submodule_search_locations is not None
        return importlib.machinery.ModuleSpec(name, _Alias(real), is_package=package)


sys.meta_path.insert(0, _Finder())
"""


def tree_at(commit: str, dest: Path) -> Path:
    """Extract the files of `commit` into `dest` (which must exist); returns `dest`. A tree
    without the `archery` package gets `ALIASES` as its `sitecustomize`."""
    archive = subprocess.run(["git", "archive", commit], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    if not (dest / "archery").is_dir():
        (dest / "sitecustomize.py").write_text(ALIASES)
    return dest


def env_for(tree: Path, **extra: str) -> dict[str, str]:
    """This process's environment with `tree`'s packages first on the path."""
    return os.environ | {"PYTHONPATH": str(tree), **extra}


def header() -> None:
    """Print the run's date and machine, the first lines of a comparison's report."""
    print(f"- Date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC")
    print(f"- Machine: {os.cpu_count()} cores, {cpu_model()}, Python {sys.version.split()[0]}")


def interleaved(repeats: int, trees: Sequence[tuple[str, T]]) -> Iterator[tuple[int, str, T]]:
    """(repeat, name, tree) for `repeats` repeats of every tree, alternating which goes first,
    so that a drift of the machine weighs on both alike."""
    for k in range(repeats):
        for name, tree in trees if k % 2 == 0 else list(trees)[::-1]:
            yield k, name, tree
