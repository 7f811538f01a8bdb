"""Shared by the hardening benchmarks (``bench/load.py``, ``bench/fuzz_upload.py``,
``bench/schemathesis_run.py``): each records its figures as ``bench/results/hardening_<name>.json``
and ``bench/results/hardening.md`` is rebuilt from all of them, with the date, machine, load
average and command of each run.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

from bench.common import DEFAULT_OUT, cpu_model, git_revision

SECTIONS = ("load", "load_memory", "fuzz_upload", "schemathesis", "cost")


def run_info() -> dict[str, Any]:
    load = os.getloadavg()
    return {
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC"),
        "machine": f"{platform.platform()}, {cpu_model()}, {os.cpu_count()} CPUs",
        "load_average": [round(x, 2) for x in load],
        "command": " ".join(shlex.quote(a) for a in [".venv/bin/python", *sys.orig_argv[1:]]),
        "git": git_revision(),
    }


def record(
    name: str, info: dict[str, Any], figures: dict[str, Any], markdown: str, out: Path = DEFAULT_OUT
) -> Path:
    """Save one benchmark's figures and rebuild ``hardening.md``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"hardening_{name}.json").write_text(
        json.dumps({"run": info, "figures": figures, "markdown": markdown}, indent=1) + "\n"
    )
    return render(out)


def render(out: Path = DEFAULT_OUT) -> Path:
    parts = [
        "# Hardening benchmarks",
        "",
        "Written by `bench/load.py`, `bench/fuzz_upload.py` and `bench/schemathesis_run.py` "
        "(each rebuilds this file from the `hardening_*.json` files beside it).",
        "",
    ]
    for name in SECTIONS:
        path = out / f"hardening_{name}.json"
        if not path.is_file():
            continue
        data = json.loads(path.read_text())
        run = data["run"]
        parts += [
            data["markdown"].rstrip(),
            "",
            f"- Date: {run['date']}; machine: {run['machine']}; load average before the run "
            f"(1/5/15 min): {' / '.join(map(str, run['load_average']))}",
            f"- Code: git {run['git']} (plus uncommitted changes, if any)",
            f"- Command: `{run['command']}`",
            "",
        ]
    target = out / "hardening.md"
    target.write_text("\n".join(parts))
    return target
