"""The pipeline benchmark without npm: it says so in its result file instead of failing."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from bench import pipelines


def test_without_npm_the_suite_writes_why(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    bins, why = pipelines.install_tools()
    assert bins is None and "npm not found" in why
    args = argparse.Namespace(out=str(tmp_path), meshes=None, seed=1)
    pipelines.run(args)
    text = (tmp_path / "pipelines.md").read_text()
    assert "**Skipped:** npm not found" in text
