"""A git revision of this repository exported as a tree beside the work tree, for benchmarks that run
the same frames through an older revision's code and this tree's in one run."""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def export_revision(revision: str, dest: Path) -> None:
    """Write ``revision``'s files into the new directory ``dest`` (``git archive``; the work tree is not
    touched). Raises OSError or CalledProcessError when git cannot export it."""
    dest.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
