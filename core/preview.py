"""Geometry for looking at a mesh: every part of a file as one small indexed triangle mesh, and
how far each vertex moved from an original (a heat map of the watermark).

The browser gets what the engine reads (the same readers and limits), so a preview never shows
a mesh the service would read differently.  Above :data:`MAX_PREVIEW_TRIANGLES` the mesh is
simplified by vertex clustering, which keeps the largest displacement of each cluster: the peaks
of the heat map survive the simplification.

Arrays in, arrays out; the HTTP layer chooses the wire format (``app.preview``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import DegenerateMeshError, MeshMarkError
from core.formats import DEFAULT_LIMITS, Limits, MeshDocument, read_mesh
from core.mesh import bbox_diagonal

#: triangles and vertices a preview holds at most (about 10 MB as float32 + uint32); above either
#: the mesh is simplified by vertex clustering until both fit
MAX_PREVIEW_TRIANGLES = 500_000
MAX_PREVIEW_VERTICES = 500_000


@dataclass(frozen=True)
class PreviewGeometry:
    """A mesh to draw, with its optional heat map.

    Attributes
    ----------
    positions : (n, 3) float32 ndarray
        Vertex positions minus ``center`` (small numbers keep float32 precise).
    triangles : (m, 3) uint32 ndarray
        Triangles into ``positions``, all parts together.
    displacement : (n,) float32 ndarray or None
        Distance each vertex moved from the original / the original's bounding-box diagonal
        (after simplification: the largest of its cluster).  ``None`` without a comparable original.
    center : (3,) float
        Bounding-box centre of the mesh, mesh units.
    diagonal : float
        Bounding-box diagonal of the mesh, mesh units.
    """

    positions: np.ndarray
    triangles: np.ndarray
    displacement: np.ndarray | None
    center: tuple[float, float, float]
    diagonal: float
    format: str
    parts: int
    source_vertices: int
    source_triangles: int
    decimated: bool
    vertices_moved: int | None = None
    max_displacement: float | None = None
    comparison: str | None = None  # why there is no displacement although an original was given


def merged_parts(doc: MeshDocument) -> tuple[np.ndarray, np.ndarray]:
    """All parts of a document as one mesh.

    Returns
    -------
    V : (n, 3) float64 ndarray
        The parts' vertices, part after part.
    F : (m, 3) int64 ndarray
        Their triangles, re-indexed into ``V``.
    """
    if not doc.parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    offsets = np.cumsum([0] + [len(p.vertices) for p in doc.parts[:-1]])
    V = np.concatenate([p.vertices for p in doc.parts])
    F = np.concatenate([p.faces + off for p, off in zip(doc.parts, offsets, strict=True)])
    return V, F


def structure_difference(original: MeshDocument, marked: MeshDocument) -> str | None:
    """Why the vertices of two documents cannot be compared one to one (``None`` when they can:
    same parts, same vertex counts, same triangles)."""
    if len(original.parts) != len(marked.parts):
        return f"the original has {len(original.parts)} mesh parts, this file {len(marked.parts)}"
    for i, (a, b) in enumerate(zip(original.parts, marked.parts, strict=True)):
        if len(a.vertices) != len(b.vertices):
            return f"part {i}: the original has {len(a.vertices):,} vertices, this file {len(b.vertices):,}"
        if not np.array_equal(a.faces, b.faces):
            return f"part {i}: the triangles differ"
    return None


def vertex_displacement(original: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """Distance each vertex moved, relative to the bounding-box diagonal of ``original``.

    Parameters
    ----------
    original, moved : (n, 3) float ndarray
        The same vertices before and after.

    Returns
    -------
    (n,) float64 ndarray
        Zero where nothing moved (and everywhere for a mesh of zero extent).
    """
    d = moved - original
    dist = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
    diag = bbox_diagonal(original)
    return dist / diag if diag > 0 else np.zeros(len(original))


def cluster_vertices(V: np.ndarray, F: np.ndarray, values: np.ndarray | None, max_triangles: int,
                     max_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Simplify by vertex clustering on a uniform grid, coarser until both caps hold (on the
    coarsest grid, 2 x 2 x 2 cells, the first ``max_triangles`` triangles are kept).

    Each occupied cell becomes one vertex at the mean of its vertices (carrying the largest of
    their ``values``); triangles whose corners fall in fewer than three cells vanish, and
    triangles repeated after the merge are kept once.  Crude next to quadric simplification, but
    vectorised, linear in the mesh and faithful enough for a thumbnail-sized view.

    Parameters
    ----------
    V : (n, 3) float ndarray
    F : (m, 3) int ndarray
    values : (n,) float ndarray or None
        Per-vertex values to carry over (maximum per cluster).
    max_triangles, max_vertices : int
        Caps for the result (at least 1).

    Returns
    -------
    V' : (n', 3) float64 ndarray
        Cluster centres, only those a triangle uses.
    F' : (m', 3) int64 ndarray
    values' : (n',) float ndarray or None
    """
    lo = V.min(axis=0)
    size = float((V.max(axis=0) - lo).max()) or 1.0
    cells = max(1, int(np.sqrt(max_triangles / 2)))  # a surface fills about cells**2 cells
    while True:
        q = np.clip(((V - lo) * (cells / size)).astype(np.int64), 0, cells)
        key = (q[:, 0] * (cells + 1) + q[:, 1]) * (cells + 1) + q[:, 2]
        _, cluster = np.unique(key, return_inverse=True)
        cluster = cluster.ravel()
        f = cluster[F]
        f = _unique_triangles(f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])],
                              int(cluster.max(initial=0)) + 1)
        if cells == 1:  # a 2 x 2 x 2 grid: at most 8 vertices; keep the first triangles that fit
            f = f[:max_triangles]
        used = np.zeros(int(cluster.max(initial=0)) + 1, bool)
        used[f.ravel()] = True
        n_used = int(used.sum())
        if (len(f) <= max_triangles and n_used <= max_vertices) or cells == 1:
            break
        shrink = min(np.sqrt(max_triangles / max(len(f), 1)), np.sqrt(max_vertices / max(n_used, 1)))
        cells = max(1, min(cells - 1, int(cells * shrink * 0.95)))
    renumber = np.cumsum(used) - 1
    f = renumber[f]
    used = np.flatnonzero(used)
    counts = np.bincount(cluster)
    centres = np.stack([np.bincount(cluster, V[:, k]) / counts for k in range(3)], axis=1)
    out_values = None
    if values is not None:
        order = np.argsort(cluster, kind="stable")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        out_values = np.maximum.reduceat(values[order], starts)[used]  # every cluster has a vertex
    return centres[used], f.astype(np.int64), out_values


def _unique_triangles(f: np.ndarray, n: int) -> np.ndarray:
    """``f`` (indices below ``n``) without triangles over the same three vertices as an earlier
    one (the first is kept)."""
    if len(f) == 0:
        return f
    s = np.sort(f, axis=1)
    if n < 2_000_000:  # n**3 fits an int64: one integer per triangle sorts much faster than rows
        keys = (s[:, 0] * n + s[:, 1]) * n + s[:, 2]
    else:
        keys = np.ascontiguousarray(s).view(np.dtype((np.void, s.itemsize * 3))).ravel()
    _, first = np.unique(keys, return_index=True)
    return f if len(first) == len(f) else f[np.sort(first)]


def _read(data: bytes, filename: str | None, limits: Limits, which: str) -> MeshDocument:
    try:
        return read_mesh(data, filename, limits)
    except MeshMarkError as exc:
        if which:
            exc.args = (f"{which}: {exc}",)
        raise


def preview_file(data: bytes, *, filename: str | None = None, original: bytes | None = None,
                 original_filename: str | None = None, limits: Limits = DEFAULT_LIMITS,
                 max_triangles: int = MAX_PREVIEW_TRIANGLES,
                 max_vertices: int = MAX_PREVIEW_VERTICES) -> PreviewGeometry:
    """The geometry of a mesh file for a viewer, with the displacement from ``original`` when
    both files have the same structure (a watermarked file and the file it was made from).

    Raises :class:`~core.errors.DegenerateMeshError` when the file has no triangle to draw; read
    errors of ``original`` say so in their message.
    """
    doc = _read(data, filename, limits, "")
    V, F = merged_parts(doc)
    if len(F) == 0:
        raise DegenerateMeshError("nothing to show: the file has no triangle")
    values: np.ndarray | None = None
    comparison = None
    if original is not None:
        before = _read(original, original_filename, limits, "original")
        comparison = structure_difference(before, doc)
        if comparison is None:
            values = vertex_displacement(merged_parts(before)[0], V)
    lo, hi = V.min(axis=0), V.max(axis=0)
    center = (lo + hi) / 2
    decimated = len(F) > max_triangles or len(V) > max_vertices
    Vp, Fp, vp = (cluster_vertices(V, F, values, max_triangles, max_vertices) if decimated
                  else (V, F, values))
    return PreviewGeometry(
        positions=(Vp - center).astype(np.float32),
        triangles=Fp.astype(np.uint32),
        displacement=None if vp is None else vp.astype(np.float32),
        center=(float(center[0]), float(center[1]), float(center[2])),
        diagonal=float(np.linalg.norm(hi - lo)),
        format=doc.format,
        parts=len(doc.parts),
        source_vertices=len(V),
        source_triangles=len(F),
        decimated=decimated,
        vertices_moved=None if values is None else int(np.count_nonzero(values)),
        max_displacement=None if values is None else float(values.max(initial=0.0)),
        comparison=comparison,
    )
