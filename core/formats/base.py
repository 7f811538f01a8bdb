"""Common model of a parsed mesh file: welded parts for the engine, patch-back writing.

Each reader (``obj``, ``ply``, ``stl``, ``off``, ``gltf``, ``tds``) returns a
:class:`MeshDocument` subclass.  A document keeps the original bytes and, per part, the
mapping from every *stored* vertex slot (file order) to its welded vertex, so that
:meth:`MeshDocument.write` can patch exactly the coordinates that moved.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from core.errors import LimitExceededError, MeshFormatError
from core.hashing import finalise64


@dataclass(frozen=True)
class Limits:
    """Resource limits checked *before* allocating (declared counts against actual bytes)."""

    max_bytes: int = 256 * 1024 * 1024
    max_vertices: int = 5_000_000
    max_faces: int = 10_000_000
    max_meshes: int = 1024
    max_json_bytes: int = 16 * 1024 * 1024

    def check(self, what: str, value: int) -> None:
        """Raise :class:`LimitExceededError` when ``value`` exceeds the limit named ``what``.

        ``what`` is one of ``"bytes"``, ``"vertices"``, ``"faces"``, ``"meshes"``, ``"json_bytes"``.
        """
        limit = getattr(self, f"max_{what}")
        if value > limit:
            raise LimitExceededError(what, int(value), int(limit))


DEFAULT_LIMITS = Limits()

#: Largest coordinate magnitude read.  The engine squares and cubes lengths (covariances, their
#: eigenvalues); beyond this, a finite file could overflow float64 there (1e154 did, in the
#: bounding-box diagonal), so it is refused as malformed instead.  float32 files store at most 3.4e38.
MAX_COORDINATE = 1e36


def check_coordinates(vertices: np.ndarray, where: str | None = None) -> None:
    """Refuse positions whose magnitude exceeds :data:`MAX_COORDINATE` (NaN included).

    Raises
    ------
    MeshFormatError
        A coordinate is not a number or larger in magnitude than :data:`MAX_COORDINATE`.
    """
    for col in np.asarray(vertices).T:  # column by column: faster than reducing an (n, 3) array
        if col.size and not max(-float(col.min()), float(col.max())) <= MAX_COORDINATE:
            raise MeshFormatError(f"a coordinate is beyond +-{MAX_COORDINATE:g} (or not a number)", where)


@dataclass
class MeshPart:
    """One triangle mesh of a file, welded for the engine.

    Attributes
    ----------
    name : str
        Mesh name from the file (object/group/node/mesh name), or ``"mesh0"``...
    vertices : (n, 3) float64
        Unique positions (exactly equal stored positions welded together).
    faces : (m, 3) int64
        Triangles into ``vertices`` (polygons fan-triangulated; faces that collapse on weld dropped).
    slot_to_vertex : (k,) int64
        For every stored vertex slot of this part, in file order, its welded vertex index.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    slot_to_vertex: np.ndarray = field(repr=False)


def _unique_rows(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Distinct rows of a C-contiguous ``(k, 3)`` float64 array, compared bit for bit.

    Rows are hashed to 64 bits and sorted by hash (a plain ``uint64`` sort, much faster than
    sorting 24-byte rows); rows of equal hash are then compared bit for bit, so the result is
    exact.  Returns ``None`` if two *different* rows share a hash (then use :func:`_unique_rows_exact`).

    Returns
    -------
    first : (n,) int64
        Slot of the first appearance of each distinct row, ascending.
    slot_to_row : (k,) int64
        For every row, the index into ``first`` of the row it equals.
    """
    k = len(pos)
    bits = pos.view(np.uint64)
    h = finalise64(bits[:, 0].copy())
    h ^= bits[:, 1]
    h = finalise64(h)
    h ^= bits[:, 2]
    h = finalise64(h)
    if k < 2 or np.all(np.diff(np.sort(h)) != 0):
        return np.arange(k, dtype=np.int64), np.arange(k, dtype=np.int64)  # all rows differ
    order = np.argsort(h)
    hs = h[order]
    start = np.empty(k, dtype=bool)
    start[0] = True
    np.not_equal(hs[1:], hs[:-1], out=start[1:])
    del h, hs
    # every row of a hash group must equal the one before it in sorted order
    dup = np.flatnonzero(~start)
    a, b = order[dup], order[dup - 1]
    if any(not np.array_equal(bits[a, c], bits[b, c]) for c in range(3)):
        return None
    del dup, a, b
    starts = np.flatnonzero(start)
    group = np.cumsum(start, dtype=np.int64) - 1  # group of each sorted row
    first_of_group = np.minimum.reduceat(order, starts)
    is_first = np.zeros(k, dtype=bool)
    is_first[first_of_group] = True
    rank = np.cumsum(is_first, dtype=np.int64) - 1  # groups numbered by first appearance
    slot_to_row = np.empty(k, dtype=np.int64)
    slot_to_row[order] = rank[first_of_group][group]
    return np.flatnonzero(is_first), slot_to_row


def _unique_rows_exact(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Same result as :func:`_unique_rows`, by sorting the 24-byte rows themselves (slower)."""
    rows = pos.view(np.dtype((np.void, 24))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return first[order].astype(np.int64), rank[inverse.ravel()].astype(np.int64)


def weld(
    positions: np.ndarray, triangles: np.ndarray, *, copy: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weld bit-identical positions.

    Parameters
    ----------
    positions : (k, 3) float
        Stored vertex positions (slots).
    triangles : (m, 3) int
        Triangles into the slots.
    copy : bool
        ``False`` lets the returned arrays be ``positions`` and ``triangles`` themselves (or
        views of them, ``-0.0`` turned into ``+0.0`` in place): for readers that discard both
        afterwards, as it saves copies of the largest arrays.

    Returns
    -------
    vertices : (n, 3) float64
        Unique positions, in order of first appearance among the slots; then, kept apart, the
        slots that share a position with a neighbouring slot, or with a slot they share two
        neighbours with (neighbours made to coincide by rounding, not copies of one vertex).
    faces : (m', 3) int64
        Triangles into ``vertices`` with degenerate (repeated-slot) triangles removed.
    slot_to_vertex : (k,) int64
        Welded index of every slot.
    """
    pos = np.ascontiguousarray(np.asarray(positions, dtype=np.float64).reshape(-1, 3))
    if not np.all(np.isfinite(pos)):
        raise MeshFormatError("non-finite vertex coordinate (NaN or Inf)")
    # turn -0.0 into +0.0 so that equal positions compare equal bytewise: in place when ``pos`` is
    # a fresh conversion or the caller gave ``positions`` up
    if not pos.flags.writeable or (copy and (pos is positions or np.may_share_memory(pos, positions))):
        pos = pos + 0.0
    else:
        pos += 0.0
    found = _unique_rows(pos)
    first, slot_to_vertex = found if found is not None else _unique_rows_exact(pos)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if tri.size and (tri.min() < 0 or tri.max() >= len(pos)):
        raise MeshFormatError("face index out of range")
    if len(first) == len(pos):  # nothing to weld: slot_to_vertex is the identity
        shared = copy and (tri is triangles or np.may_share_memory(tri, triangles))
        return pos, nondegenerate(tri, shared), slot_to_vertex
    vertices = pos[first]
    faces = slot_to_vertex[tri] if tri.size else np.zeros((0, 3), np.int64)
    # Slots that share a position are copies of one vertex (UV seams, STL soups) or neighbours
    # that a rounding (quantisation, float32) made coincide.  Welding copies gives a manifold
    # vertex; welding neighbours collapses an edge (two corners of one triangle) or makes an edge
    # of more than two faces out of different ones (two vertices with a common neighbour): keep
    # such slots apart.
    split = _coinciding_neighbours(tri, faces, slot_to_vertex)
    if split.size:
        slot_to_vertex = slot_to_vertex.copy()
        slot_to_vertex[split] = len(vertices) + np.arange(split.size)
        vertices = np.concatenate([vertices, pos[split]])
        faces = slot_to_vertex[tri]
    return vertices, nondegenerate(faces, False), slot_to_vertex


def _coinciding_neighbours(tri: np.ndarray, faces: np.ndarray, slot_to_vertex: np.ndarray) -> np.ndarray:
    """Slots (sorted) that welding would join to a neighbour: two slots of one triangle at one
    position, or the welded corners of an edge that more than two triangles use and that welding
    made out of different slot edges (a slot edge the file itself shares three times is left
    alone: non-manifold CAD edges are not a rounding), when the slot has faces of its own (a soup's
    corners are welded regardless: apart, they would have no neighbour at all)."""
    clash = np.zeros(tri.shape, bool)
    for a, b in ((0, 1), (1, 2), (0, 2)):
        same = (faces[:, a] == faces[:, b]) & (tri[:, a] != tri[:, b])
        clash[:, a] |= same
        clash[:, b] |= same
    m = len(tri)
    if m:
        ends = ((0, 1), (1, 2), (2, 0))
        fa = np.concatenate([faces[:, i] for i, _ in ends])
        fb = np.concatenate([faces[:, j] for _, j in ends])
        n = int(faces.max()) + 1
        key = np.where(fa != fb, np.minimum(fa, fb) * n + np.maximum(fa, fb), -1)
        ordered = np.sort(key)
        # welded edges of three or more faces: rare, so find their keys first (one sort) and
        # only then their face-edges
        crowded_keys = np.unique(ordered[2:][(ordered[2:] == ordered[:-2]) & (ordered[2:] >= 0)])
        if crowded_keys.size:
            crowded = np.flatnonzero(np.isin(key, crowded_keys))
            sa = np.concatenate([tri[:, i] for i, _ in ends])[crowded]
            sb = np.concatenate([tri[:, j] for _, j in ends])[crowded]
            k = int(tri.max()) + 1
            edge = np.searchsorted(crowded_keys, key[crowded])
            slot_edge = np.minimum(sa, sb) * k + np.maximum(sa, sb)
            pairs = np.unique(np.stack([edge, slot_edge], 1), axis=0)
            made = np.bincount(pairs[:, 0], minlength=len(crowded_keys)) > 1  # from different slot edges
            hit = crowded[made[edge]]
            rows, which = hit % m, hit // m
            # a slot of a single face (an STL soup's corner) would be left without any neighbour:
            # only slots with connectivity of their own are kept apart this way
            shared = np.bincount(tri.ravel(), minlength=k) > 1
            for e, (i, j) in enumerate(ends):
                r = rows[which == e]
                clash[r, i] |= shared[tri[r, i]]
                clash[r, j] |= shared[tri[r, j]]
    if not clash.any():
        return np.zeros(0, np.int64)
    candidates = np.unique(tri[clash])
    # only slots that share their welded vertex with another slot are split off, and of a vertex
    # whose every slot would be, the first stays on it (else it would be left without a slot or a
    # face: 8-bit quantisation left the Ogre 8,157 such isolated vertices, 13 % more than it has)
    sizes = np.bincount(slot_to_vertex)
    split = candidates[sizes[slot_to_vertex[candidates]] > 1]
    group = slot_to_vertex[split]
    whole = np.bincount(group, minlength=len(sizes)) == sizes
    _, first = np.unique(group, return_index=True)
    keep = np.ones(split.size, bool)
    keep[first[whole[group[first]]]] = False
    return split[keep]


def nondegenerate(faces: np.ndarray, copy: bool) -> np.ndarray:
    """``faces`` without the triangles that repeat a vertex (a copy when ``copy`` and none is dropped)."""
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    if keep.all():  # the usual case; a boolean selection would copy the array much more slowly
        return faces.copy() if copy else faces
    return faces[keep]


def fan_triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given as a flat index list.

    Parameters
    ----------
    counts : (p,) int
        Number of corners of each polygon (>= 3).
    indices : (sum(counts),) int
        Corner indices, polygon after polygon.

    Returns
    -------
    (sum(max(counts - 2, 0)), 3) int64 triangles: a polygon of fewer than 3 corners (a point
    or an edge written as a face, as some exporters do) gives none.
    """
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    if counts.size == 0:
        return np.zeros((0, 3), np.int64)
    if counts.min() < 0:
        raise MeshFormatError("polygon with a negative number of corners")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ntri = np.maximum(counts - 2, 0)
    poly = np.repeat(np.arange(counts.size), ntri)
    k = np.arange(ntri.sum()) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    s = starts[poly]
    return np.stack([indices[s], indices[s + k + 1], indices[s + k + 2]], axis=1)


def strip_triangles(counts: np.ndarray, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Triangle strips as triangles: ``(counts, flat, joins)`` of the triangles of the strips of
    records of ``counts`` indices each (``flat``, record after record; ``-1`` ends a strip and
    starts the next within a record), every other triangle of a strip turned to keep its
    orientation (``b, a, c`` for the strip's ``a, b, c`` at odd positions).  ``joins``: the
    triangles that repeat a corner (the degenerate triangles writers put between pieces of one
    strip; the weld drops them)."""
    counts = np.asarray(counts, np.int64)
    flat = np.asarray(flat, np.int64)
    n = flat.size
    if n < 3:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), 0
    # where a strip starts: a record's first index, or the one after a -1
    start = np.zeros(n, bool)
    start[(np.cumsum(counts) - counts)[counts > 0]] = True
    start[1:] |= flat[:-1] < 0
    first = np.maximum.accumulate(np.where(start, np.arange(n), 0))
    i = np.arange(n - 2)
    # three indices of one strip in a row (no -1 among them, no strip starting at i + 1 or i + 2)
    ok = (flat[:-2] >= 0) & (flat[1:-1] >= 0) & (flat[2:] >= 0) & (first[2:] == first[:-2])
    i = i[ok]
    odd = ((i - first[i]) & 1).astype(bool)
    a, b, c = flat[i], flat[i + 1], flat[i + 2]
    tri = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)
    joins = int(np.count_nonzero((a == b) | (b == c) | (a == c)))
    return np.full(len(tri), 3, np.int64), tri.reshape(-1), joins


class MeshDocument:
    """A parsed mesh file.

    Subclasses set the attributes below and implement :meth:`_patch`.

    Attributes
    ----------
    format : str
        The name of its :class:`FormatSpec` (``"obj"``, ``"glb"``...).
    encoding : str
        ``"ascii"``, ``"binary_little_endian"``, ``"binary_big_endian"`` (PLY, and ``"binary"``
        for STL/GLB/3DS).
    parts : list of MeshPart
        Welded meshes.
    decimals : int or None
        Text formats: decimals used when printing moved coordinates (the most found in the
        source's vertex lines); ``None`` for binary formats and exponent notation.
    skipped_elements : int
        Elements of the file that give the engine no triangle and are carried through untouched:
        faces of fewer than 3 distinct corners, OBJ ``l``/``p`` lines, glTF point and line
        primitives.
    reencoded : list of str
        After :meth:`write`: the compressed encodings whose streams had to be re-encoded
        (``"draco"``, ``"meshopt"``); empty when every other byte was kept.
    storage_dtype : numpy dtype or None
        Binary formats: dtype of stored coordinates (float32 mostly).
    """

    format: str = ""
    encoding: str = ""
    decimals: int | None = None
    storage_dtype: np.dtype | None = None
    skipped_elements: int = 0
    reencoded: tuple[str, ...] = ()

    def __init__(self, data: bytes, parts: list[MeshPart]) -> None:
        self.data = data
        self.parts = parts

    def quantize(self, vertices: np.ndarray, decimals: int | None = None) -> np.ndarray:
        """Positions as a :meth:`write` then a new read would give them back.

        Parameters
        ----------
        vertices : (n, 3) float64
        decimals : int, optional
            Text formats: override of :attr:`decimals`.
        """
        v = np.asarray(vertices, dtype=np.float64)
        if self.storage_dtype is not None:
            return v.astype(self.storage_dtype).astype(np.float64)
        d = self.decimals if decimals is None else decimals
        if d is None:
            return v
        return np.round(v, d)

    def quantize_part(self, part: int, index: np.ndarray, vertices: np.ndarray,
                      decimals: int | None = None) -> np.ndarray:
        """:meth:`quantize` for the vertices ``index`` of part ``part`` (formats whose parts or
        vertices are stored on different grids, such as quantized glTF, override it)."""
        return self.quantize(vertices, decimals)

    def write(self, vertices: list[np.ndarray], decimals: int | None = None) -> bytes:
        """Bytes of the same file with the parts' vertices at the new positions.

        Only vertex slots whose welded vertex moved are rewritten; every other byte is kept.

        Parameters
        ----------
        vertices : list of (n_i, 3) float64
            New welded positions, one array per part (same shapes as ``parts[i].vertices``).
        decimals : int, optional
            Text formats: digits after the decimal point for rewritten coordinates.
        """
        if len(vertices) != len(self.parts):
            raise ValueError("one vertex array per part expected")
        moved: list[np.ndarray] = []
        for part, v in zip(self.parts, vertices, strict=True):
            v = np.asarray(v, dtype=np.float64)
            if v.shape != part.vertices.shape:
                raise ValueError(f"part {part.name!r}: expected shape {part.vertices.shape}, got {v.shape}")
            old = part.vertices
            # column by column: much faster than np.any(v != old, axis=1) on (n, 3) arrays
            changed = (v[:, 0] != old[:, 0]) | (v[:, 1] != old[:, 1]) | (v[:, 2] != old[:, 2])
            moved.append(np.flatnonzero(changed))
        return self._patch(vertices, moved, decimals)

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        raise NotImplementedError


@dataclass(frozen=True)
class FormatSpec:
    """Everything the rest of MeshMark knows of one format; each reader module exports its own
    (``SPEC``, or ``SPECS`` for a module that reads two formats), and :mod:`core.formats` lists
    them.  Extensions, media types, messages and documentation are derived from these.

    Attributes
    ----------
    name : str
        Format key, as in :attr:`MeshDocument.format` (``"ply"``).
    label : str
        How documentation names it (``"PLY"``, ``"glTF"``).
    family : str
        How error messages name it; formats of one family are named once (``"glTF/GLB"``).
    extensions : tuple of str
        File-name extensions, lower case, without the dot; the first names the answer's file.
    media_type : str
        ``Content-Type`` of a file of this format.
    sniff : callable
        ``sniff(data, name) -> bool``: the content is this format (``name`` is this spec's, for
        modules that read two formats).
    read : callable
        ``read(data, limits, name) -> MeshDocument``.
    sniff_rank : int
        Contents are sniffed by increasing rank.  0: a signature in the first bytes that no other
        format's file starts with; a format recognised by a weaker test (binary STL by its size
        alone, OFF by its first token, OBJ by its statements) ranks after the formats whose
        files it could be mistaken for.
    why_not : callable, optional
        ``why_not(data) -> str``: a hint appended to the refusal of a file whose extension names
        this format but whose content matches none.
    """

    name: str
    label: str
    family: str
    extensions: tuple[str, ...]
    media_type: str
    sniff: Callable[[bytes, str], bool]
    read: Callable[[bytes, Limits, str], MeshDocument]
    sniff_rank: int = 0
    why_not: Callable[[bytes], str] | None = None

    @property
    def extension(self) -> str:
        """The canonical extension (of the answer's file name)."""
        return self.extensions[0]
