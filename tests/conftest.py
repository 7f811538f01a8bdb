"""Shared fixtures.

Real meshes come from one setting: ``MESHMARK_TEST_MESHES`` (default ``../shared/meshes``,
relative to the repository root).  Tests needing them skip with a visible reason when absent.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MESHES_DIR = (ROOT / os.environ.get("MESHMARK_TEST_MESHES", "../shared/meshes")).resolve()
if "MESHMARK_TEST_MESHES" not in os.environ and not MESHES_DIR.is_dir():
    # a clone outside the workspace (CI's clean clone): the workspace's shared folder
    MESHES_DIR = Path("/work/shared/meshes")

SHARED_MESHES = [
    "teapot.stl", "monkey.glb", "sink.3ds", "spot.obj", "decimated-max.obj", "fandisk.off",
    "rocker-arm.obj", "beetle.off", "bun_zipper.ply", "armadillo.obj", "horse.ply", "dragon.ply",
    "turbineblade.ply", "Duck.glb", "CesiumMilkTruck.glb",
]


def shared_mesh_path(name: str) -> Path:
    """Path of a shared mesh, or skip the test with the reason."""
    path = MESHES_DIR / name
    if not path.is_file():
        pytest.skip(f"shared mesh {name} not found in {MESHES_DIR} (set MESHMARK_TEST_MESHES)")
    return path


@pytest.fixture(scope="session", autouse=True)
def _registry_outside_the_repository(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Apps and servers started with default settings keep their registry of copies in a temporary
    folder, not in the working directory (``MESHMARK_REGISTRY_PATH``, unless the run sets it)."""
    name = "MESHMARK_REGISTRY_PATH"
    before = os.environ.get(name)
    if before is None:
        os.environ[name] = str(tmp_path_factory.mktemp("registry") / "registry.sqlite3")
    yield
    if before is None:
        os.environ.pop(name, None)


@pytest.fixture
def meshes_dir() -> Path:
    if not MESHES_DIR.is_dir():
        pytest.skip(f"shared meshes not found at {MESHES_DIR} (set MESHMARK_TEST_MESHES)")
    return MESHES_DIR
