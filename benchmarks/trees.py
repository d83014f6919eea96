"""The code of an earlier commit beside this tree, for benchmarks that compare the two in one
run: `git archive COMMIT` extracted into a folder, run with this interpreter and environment
(`PYTHONPATH` set to the folder, so its packages shadow this tree's)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

__all__ = ["ROOT", "env_for", "tree_at"]

ROOT = Path(__file__).resolve().parents[1]


def tree_at(commit: str, dest: Path) -> Path:
    """Extract the files of `commit` into `dest` (which must exist); returns `dest`."""
    archive = subprocess.run(["git", "archive", commit], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest


def env_for(tree: Path, **extra: str) -> dict[str, str]:
    """This process's environment with `tree`'s packages first on the path."""
    return os.environ | {"PYTHONPATH": str(tree), **extra}
