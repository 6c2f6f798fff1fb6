"""Running the ``curvimesh`` command in a real subprocess, for the CLI tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def run_cli(
    *args: str, cwd: Path, stdin: bytes | str | None = None, text: bool = False
) -> subprocess.CompletedProcess:
    """``python -m curvimesh ARGS`` in ``cwd``, output captured, never raising on failure."""
    return subprocess.run(
        [sys.executable, "-m", "curvimesh", *args],
        input=stdin,
        capture_output=True,
        text=text,
        cwd=cwd,
        check=False,
    )
