"""The README's commands and programs, run as a reader would: against a real ``meshmark serve``, in
a scratch folder holding the shared meshes under the README's names.  A documented command that
fails fails here.  A block whose previous line is ``<!-- not run: reason -->`` is skipped."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.app.real_server import serve
from tests.conftest import ROOT, shared_mesh_path

README = ROOT / "README.md"
#: the README's file names -> the shared meshes
FILES = {"bunny.ply": "bun_zipper.ply", "spot.obj": "spot.obj", "dragon.ply": "dragon.ply",
         "catalogue/Duck.glb": "Duck.glb", "catalogue/monkey.glb": "monkey.glb"}
_FENCE = re.compile(r"^```(\w*)\n(.*?)^```\n", re.M | re.S)


@dataclass(frozen=True)
class Block:
    line: int
    lang: str
    code: str
    skip: str | None


def blocks() -> list[Block]:
    text = README.read_text()
    found = []
    for match in _FENCE.finditer(text):
        before = text[:match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        skip = re.fullmatch(r"<!-- not run: (.+) -->", before)
        found.append(Block(text.count("\n", 0, match.start()) + 1, match.group(1), match.group(2),
                           skip.group(1) if skip else None))
    return found


RUNNABLE = [b for b in blocks() if b.lang in ("sh", "python")]


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    """The folder the examples run in, and the server they talk to (its port in place of 8000)."""
    folder = tmp_path_factory.mktemp("readme")
    for name, shared in FILES.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(shared_mesh_path(shared), folder / name)
    with serve(folder.parent / "readme-server.log") as server:
        yield folder, server


def test_every_block_is_run_or_says_why_not():
    assert len(RUNNABLE) >= 8
    assert {b.lang for b in blocks()} <= {"sh", "python", "text"}  # nothing left unchecked by accident


def test_curl_examples_never_save_a_problem_as_a_mesh():
    """``--fail-with-body``: an error answer is a non-zero exit; ``--remove-on-error`` with ``-o``:
    the problem is not left behind under the mesh's name."""
    commands = [cmd for b in RUNNABLE if b.lang == "sh" and not b.skip
                for cmd in re.split(r"\n(?!\s)", b.code.replace("\\\n", " ")) if "curl " in cmd]
    assert commands
    for cmd in commands:
        assert "--fail-with-body" in cmd, cmd
        if re.search(r"-o (?!/dev/null)", cmd):
            assert "--remove-on-error" in cmd, cmd


@pytest.mark.parametrize("block", RUNNABLE, ids=[f"line-{b.line}-{b.lang}" for b in RUNNABLE])
def test_readme_block_runs(block, scratch):
    if block.skip:
        pytest.skip(block.skip)
    folder, server = scratch
    code = block.code.replace("127.0.0.1:8000", f"127.0.0.1:{server.port}")
    env = {k: v for k, v in os.environ.items() if not k.startswith("MESHMARK_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    command = (["bash", "-e", "-o", "pipefail", "-c", code] if block.lang == "sh"
               else [sys.executable, "-c", code])
    result = subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, (f"README line {block.line} failed ({result.returncode}):\n{code}\n"
                                    f"--- stdout\n{result.stdout[-2000:]}\n"
                                    f"--- stderr\n{result.stderr[-3000:]}")
