"""Every command in the README's ```sh blocks runs, in order, and succeeds.

The commands run with bash (``pipefail``) in a temporary copy of ``metrics/``,
with this interpreter's ``bin`` directory first on ``PATH`` (for
``curvimesh``), so a renamed command or option, or a broken example, fails
here. Three kinds of line are skipped, and only these (:data:`SKIPPED`):
``make`` targets (they build a venv and run the whole suite), the ``gmsh``
GUI, and activating the venv (done by ``PATH`` here).

Substitution, for speed: in a command that adapts (one that runs any of
:data:`ADAPTING`), ``metrics/NAME.yaml`` becomes ``small/NAME.yaml``, a
coarse isotropic metric on the same box with the same name, so that
``adapt`` or ``batch metrics/*.yaml`` take seconds instead of minutes. The
other commands (``report``, ``check-metric``, ``geodesic``, ``circles``) use
the real metric files, on the meshes the commands before them made.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: Line prefixes that are not run, and why.
SKIPPED = {
    "make ": "builds the venv and runs whole suites; tested by CI itself",
    "gmsh ": "opens the Gmsh GUI",
    ". .venv/bin/activate": "PATH already points at this interpreter's bin",
}
#: Subcommands that adapt a mesh to a metric: their metric files become small ones.
ADAPTING = ("adapt", "sample", "triangulate", "curve", "swap", "batch")
SMALL = "name: {name}\ndomain:\n  box: [[-2, -2], [2, 2]]\nmetric:\n  isotropic: 0.6\n"


def sh_commands(text: str) -> list[str]:
    """The commands of the ```sh blocks of ``text``, continuation lines joined."""
    commands = []
    for block in re.findall(r"^```sh\n(.*?)^```", text, flags=re.M | re.S):
        joined = re.sub(r"\\\n\s*", "", block)
        commands += [line.strip() for line in joined.splitlines() if line.strip()]
    return commands


def is_skipped(command: str) -> bool:
    return command.startswith(tuple(SKIPPED))


def adapts(command: str) -> bool:
    return any(re.search(rf"\bcurvimesh\s+{verb}\b", command) for verb in ADAPTING)


def test_sh_commands_parses_blocks_and_continuations():
    text = "```sh\na \\\n  | b\n\nc  # note\n```\n```python\nd\n```\n```sh\ne\n```\n"
    assert sh_commands(text) == ["a | b", "c  # note", "e"]
    assert adapts("curvimesh sample -o - | curvimesh swap -")
    assert not adapts("curvimesh report a.msh --metric metrics/toy.yaml")


def test_the_readme_starts_with_the_two_set_up_commands():
    first = sh_commands(README.read_text(encoding="utf-8"))[:2]
    assert [c.split("#")[0].strip() for c in first] == ["make demo", "make test"]


def test_the_readme_pictures_exist():
    text = README.read_text(encoding="utf-8")
    pictures = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text)
    assert pictures
    for rel in pictures:
        assert (ROOT / rel).is_file(), rel


def test_every_readme_command_runs(tmp_path):
    commands = sh_commands(README.read_text(encoding="utf-8"))
    shutil.copytree(ROOT / "metrics", tmp_path / "metrics")
    (tmp_path / "small").mkdir()
    for path in (ROOT / "metrics").glob("*.yaml"):
        (tmp_path / "small" / path.name).write_text(SMALL.format(name=path.stem))
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    ran = 0
    for command in commands:
        if is_skipped(command):
            continue
        run = command.replace("metrics/", "small/") if adapts(command) else command
        r = subprocess.run(
            ["bash", "-o", "pipefail", "-c", run],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            check=False,
            timeout=300,
        )
        if r.returncode != 0:
            pytest.fail(f"README command failed ({r.returncode}): {command}\n{r.stderr[-2000:]}")
        ran += 1
    assert ran >= 10  # the tour is there, and most of it is not skipped
    for made in ("toy.msh", "stats.json", "toy.png", "circles.png", "runs/summary.json"):
        assert (tmp_path / made).is_file(), made
