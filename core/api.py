"""The engine's public face, for the service, the command line and the benchmarks.

File level (bytes in, bytes or a report out): :func:`embed`, :func:`detect` and :func:`capacity`
take an :class:`~core.options.Options` checked once by whoever built it (the service's forms, the
command line); :func:`embed_file`, :func:`detect_file` and :func:`capacity_file` take the same
choices as keywords.  Array level: :func:`embed_mesh` and :func:`detect_mesh`.  None of them
touches HTTP, paths, the environment or the network.
"""

from __future__ import annotations

from core.options import AUTO_METHOD, DEFAULT_METHOD, METHODS, Options
from core.pipeline import (
    capacity,
    capacity_file,
    detect,
    detect_file,
    detect_mesh,
    embed,
    embed_file,
    embed_mesh,
)
from core.reports import CapacityReport, DetectResult, EmbeddedFile, EmbedReport, Progress

__all__ = [
    "AUTO_METHOD",
    "DEFAULT_METHOD",
    "METHODS",
    "CapacityReport",
    "DetectResult",
    "EmbedReport",
    "EmbeddedFile",
    "Options",
    "Progress",
    "capacity",
    "capacity_file",
    "detect",
    "detect_file",
    "detect_mesh",
    "embed",
    "embed_file",
    "embed_mesh",
]
