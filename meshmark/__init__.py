"""MeshMark's Python client (:mod:`meshmark.client`) and version.

The service itself lives in the top-level packages ``app`` (HTTP, workers, CLI) and ``core`` (the
engine); this package imports neither, so a program that only calls a MeshMark server needs httpx
and nothing else of ours.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("meshmark")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
