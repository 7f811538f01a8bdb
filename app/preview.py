"""The wire format of ``POST /v1/preview``: one binary answer a browser maps straight onto typed
arrays, without parsing numbers.

Layout (little-endian throughout)::

    uint32                header length H (bytes, a multiple of 4)
    H bytes               JSON header, UTF-8, padded with spaces
    float32[n * 3]        positions (mesh units, minus "center")
    uint32[m * 3]         triangles, all parts together
    float32[n]            displacement / bounding-box diagonal (only when "displacement" is true)

Every array starts on a 4-byte boundary.  The header says ``vertices`` (n), ``triangles`` (m) and
how the mesh was read (:func:`header`).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from core.preview import MAX_PREVIEW_TRIANGLES, MAX_PREVIEW_VERTICES, PreviewGeometry

PREVIEW_MEDIA_TYPE = "application/vnd.meshmark.preview"

PREVIEW_DESCRIPTION = f"""The mesh for a viewer, as `{PREVIEW_MEDIA_TYPE}` (little-endian):
a `uint32` header length H, H bytes of JSON (padded with spaces), then `float32` positions
(n x 3, relative to `center`), `uint32` triangles (m x 3, all mesh parts together) and, when the
header's `displacement` is true, `float32` per-vertex displacement / bounding-box diagonal (n).

JSON header: `vertices` (n), `triangles` (m), `source_vertices`, `source_triangles`, `parts`,
`format`, `center` (3 numbers), `diagonal`, `decimated`, `displacement` (bool),
`vertices_moved`, `max_displacement` (relative to the diagonal) and `comparison` (why the
displacement is missing although an `original` was sent, else null).

At most {MAX_PREVIEW_TRIANGLES:,} triangles and {MAX_PREVIEW_VERTICES:,} vertices are sent: above
either, the mesh is simplified by vertex clustering (`decimated`: true) and each remaining vertex
carries the largest displacement of the vertices it stands for."""


def header(geometry: PreviewGeometry) -> dict[str, Any]:
    return {
        "vertices": len(geometry.positions),
        "triangles": len(geometry.triangles),
        "source_vertices": geometry.source_vertices,
        "source_triangles": geometry.source_triangles,
        "parts": geometry.parts,
        "format": geometry.format,
        "center": list(geometry.center),
        "diagonal": geometry.diagonal,
        "decimated": geometry.decimated,
        "displacement": geometry.displacement is not None,
        "vertices_moved": geometry.vertices_moved,
        "max_displacement": geometry.max_displacement,
        "comparison": geometry.comparison,
    }


def _little_endian(array: np.ndarray, dtype: str) -> memoryview:
    """The bytes of ``array`` as C-contiguous little-endian ``dtype`` (no copy when it is that)."""
    return np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<")).data


def pack(geometry: PreviewGeometry) -> bytes:
    """The answer body for ``geometry`` (layout in the module docstring).  It is rendered in the
    server process, so the arrays are copied once, straight into the body."""
    text = json.dumps(header(geometry), separators=(",", ":"), allow_nan=False).encode()
    text += b" " * (-len(text) % 4)
    chunks = [memoryview(len(text).to_bytes(4, "little")), memoryview(text),
              _little_endian(geometry.positions, "f4"), _little_endian(geometry.triangles, "u4")]
    if geometry.displacement is not None:
        chunks.append(_little_endian(geometry.displacement, "f4"))
    return b"".join(chunks)


def unpack(body: bytes) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray | None]:
    """The inverse of :func:`pack` (for tests and Python clients): header, positions (n, 3),
    triangles (m, 3) and displacement (n,) or ``None``."""
    size = int.from_bytes(body[:4], "little")
    head = json.loads(body[4:4 + size])
    n, m = head["vertices"], head["triangles"]
    offset = 4 + size
    positions = np.frombuffer(body, "<f4", n * 3, offset).reshape(n, 3)
    offset += 12 * n
    triangles = np.frombuffer(body, "<u4", m * 3, offset).reshape(m, 3)
    offset += 12 * m
    displacement = np.frombuffer(body, "<f4", n, offset) if head["displacement"] else None
    expected = offset + (4 * n if head["displacement"] else 0)
    if len(body) != expected:
        raise ValueError(f"preview body has {len(body)} bytes, the header describes {expected}")
    return head, positions, triangles, displacement

