"""Shared fixtures.

Real meshes come from one setting: ``MESHMARK_TEST_MESHES`` (default ``../shared/meshes``,
relative to the repository root).  Tests needing them skip with a visible reason when absent.
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from collections import Counter
from pathlib import Path

import pytest

from tests.shared import meshes_dir as _meshes_dir  # the one setting, for bench and tests

ROOT = Path(__file__).resolve().parents[1]
MESHES_DIR = _meshes_dir()

# apps and servers started with default settings (``app.main.app`` is built when it is imported,
# before any fixture runs) keep their registry of copies in a temporary folder, not in the working
# directory, unless the run sets MESHMARK_REGISTRY_PATH itself
if "MESHMARK_REGISTRY_PATH" not in os.environ:
    _REGISTRY_DIR = tempfile.mkdtemp(prefix="meshmark-test-registry-")
    os.environ["MESHMARK_REGISTRY_PATH"] = str(Path(_REGISTRY_DIR) / "registry.sqlite3")
    atexit.register(shutil.rmtree, _REGISTRY_DIR, True)

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


@pytest.fixture
def meshes_dir() -> Path:
    if not MESHES_DIR.is_dir():
        pytest.skip(f"shared meshes not found at {MESHES_DIR} (set MESHMARK_TEST_MESHES)")
    return MESHES_DIR


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test its own node id (:func:`_unique_node_ids`), then the tests marked ``slow`` first,
    the others in their order: under pytest-xdist's ``--dist loadfile --no-loadscope-reorder``
    (scripts/test) their files are then the first handed out, so the longest test runs beside the
    rest of the suite instead of after it."""
    _unique_node_ids(items)
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def _unique_node_ids(items: list[pytest.Item]) -> None:
    """pytest 9 builds an item's node id from its function's name and its parametrization;
    schemathesis 4 makes one item per API operation with no parametrization, so the 15 operations
    of tests/app/test_hardening_schema.py shared one node id, and pytest-xdist, which hands tests
    out by node id, ran one of the 15 (and reported 1,078 passed of 1,092).  Every such item gets
    its operation as the id's parameter (``test_api_conforms_to_its_document[POST /v1/embed]``,
    the name pytest already shows); a duplicate left after that stops the run."""
    for item in items:
        label = getattr(item, "operation_label", None)  # a schemathesis item's operation
        if label and item._id.params is None:
            item._id = item._id.with_params(str(label))  # no public setter for a node's id
    left = sorted(nodeid for nodeid, count in Counter(item.nodeid for item in items).items() if count > 1)
    if left:
        raise pytest.UsageError(f"tests sharing a node id (pytest-xdist would run one of each): {left}")
