"""Where the shared meshes are: the one setting that the tests and the benchmarks read."""

from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: where a clone outside the workspace (CI's clean clone) finds the shared meshes when no
#: ``MESHMARK_TEST_MESHES`` says otherwise
WORKSPACE_MESHES = Path("/work/shared/meshes")


def meshes_dir() -> Path:
    """``$MESHMARK_TEST_MESHES`` relative to the repository root (default ``../shared/meshes``;
    unset, and no such folder there: :data:`WORKSPACE_MESHES`)."""
    path = (ROOT / os.environ.get("MESHMARK_TEST_MESHES", "../shared/meshes")).resolve()
    if "MESHMARK_TEST_MESHES" not in os.environ and not path.is_dir():
        return WORKSPACE_MESHES
    return path
