"""The repository's root, and the files of a git checkout that git does not track (the
session check in conftest that the tests write only into pytest's temp folders)."""

from __future__ import annotations

import contextlib
import os
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# Written by Python, pytest and the linters wherever they run: not the suite's doing.
CACHES = frozenset({".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", ".mypy_cache"})


def untracked_files(root: Path, skip: Path | None = None) -> dict[str, tuple[int, int]] | None:
    """``{path: (size, mtime_ns)}`` of every file in git checkout ``root`` that git does not
    track (untracked and ignored ones: ``mlruns/``, ``mlflow.db``, its lock ...), caches and
    ``skip`` left out; None when ``root`` is not the top of a git checkout."""
    try:
        top = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--show-toplevel"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        listed = subprocess.run(
            ["git", "-C", str(root), "ls-files", "-z"], capture_output=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    if Path(top).resolve() != root.resolve():
        return None
    tracked = set(os.fsdecode(listed).split("\0"))
    found = {}
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        dirs[:] = [d for d in dirs if d not in CACHES and (skip is None or here / d != skip)]
        for name in files:
            path = here / name
            relative = path.relative_to(root).as_posix()
            if relative not in tracked:
                with contextlib.suppress(OSError):  # removed meanwhile
                    stat = path.lstat()
                    found[relative] = (stat.st_size, stat.st_mtime_ns)
    return found


def ignored(root: Path, paths: list[str]) -> list[str]:
    """Those of ``paths`` (relative to git checkout ``root``) that git ignores, sorted."""
    if not paths:
        return []
    found = subprocess.run(
        ["git", "-C", str(root), "check-ignore", "-z", "--stdin"],
        input="\0".join(paths).encode(),
        capture_output=True,
    ).stdout
    return sorted(p for p in os.fsdecode(found).split("\0") if p)
