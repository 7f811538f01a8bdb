"""Attacks on triangle meshes, as pure numpy functions.

Every attack has the signature ``attack(vertices, faces, level, rng) -> (vertices, faces)``:

V : (n, 3) float64 ndarray
    Vertex positions. Not modified.
F : (m, 3) int64 ndarray
    Triangle indices into V. Not modified.
level : float or str
    Strength of the attack in the unit documented by each function (see :data:`ATTACKS`).
rng : numpy.random.Generator
    The only source of randomness, so that a seed reproduces an attack exactly.

The attacked mesh is returned as new arrays; the benchmarks write it as a binary PLY with
``double`` coordinates (no quantisation added) and hand the bytes to ``detect_file``.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from tests.core.meshes import sqrt3_subdivide

Attack = Callable[[np.ndarray, np.ndarray, Any, np.random.Generator], tuple[np.ndarray, np.ndarray]]


# ---------------------------------------------------------------------------------------------
# helpers


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(e, 2) int64 undirected edges of ``faces``, each once, smaller index first."""
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def adjacency_matrix(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """(n, n) symmetric 0/1 CSR matrix of the 1-ring adjacency."""
    e = unique_edges(faces)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))


def ring_distance(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """D(V_i) of Bors 2006 eq. (5): sum of squared distances to the 1-ring neighbours, (n,)."""
    v = np.asarray(vertices, np.float64)
    e = unique_edges(faces)
    d2 = np.sum((v[e[:, 0]] - v[e[:, 1]]) ** 2, axis=1)
    return np.bincount(e[:, 0], d2, len(v)) + np.bincount(e[:, 1], d2, len(v))


def mean_centroid_distance(vertices: np.ndarray) -> float:
    v = np.asarray(vertices, np.float64)
    return float(np.mean(np.linalg.norm(v - v.mean(axis=0), axis=1)))


def drop_unreferenced(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove vertices no face uses, keeping the order of the others."""
    used = np.zeros(len(vertices), bool)
    used[np.asarray(faces, np.int64).ravel()] = True
    remap = np.cumsum(used) - 1
    return np.asarray(vertices)[used].copy(), remap[faces].astype(np.int64)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniformly distributed 3x3 rotation (QR of a Gaussian matrix with the sign fix)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# attacks


def none(vertices, faces, level, rng):
    """No attack: the mesh is only rewritten (checks that the writer path itself is transparent)."""
    return np.array(vertices, np.float64), np.array(faces, np.int64)


def similarity(vertices, faces, level, rng):
    """Random rotation (uniform over SO(3)), isotropic scale log-uniform in [0.1, 10], translation
    uniform in [-10, 10] bounding-box diagonals per axis.  ``level`` is unused."""
    v = np.asarray(vertices, np.float64)
    rot = random_rotation(rng)
    scale = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) if len(v) else 1.0
    shift = rng.uniform(-10.0, 10.0, 3) * diag
    return scale * (v @ rot.T) + shift, np.array(faces, np.int64)


def reorder(vertices, faces, level, rng):
    """Random permutation of the vertices and of the faces, faces remapped, and each face's corners
    rotated cyclically by a random amount (orientation kept).  ``level`` is unused."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    perm = rng.permutation(len(v))  # new vertex k is old vertex perm[k]
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(v))
    f2 = inv[f][rng.permutation(len(f))]
    shift = rng.integers(0, 3, len(f2))
    idx = (np.arange(3)[None, :] + shift[:, None]) % 3
    f2 = np.take_along_axis(f2, idx, axis=1)
    return v[perm].copy(), f2


def uniform_noise(vertices, faces, level, rng):
    """Additive noise uniform in [-A, A] on every coordinate, A = ``level`` x mean distance of the
    vertices to their centroid (``level`` = 0.001 is 0.1 %)."""
    v = np.asarray(vertices, np.float64)
    a = float(level) * mean_centroid_distance(v)
    return v + rng.uniform(-a, a, v.shape), np.array(faces, np.int64)


def gaussian_sigma(vertices, faces, e: float) -> float:
    """Noise deviation sigma for a normalized displacement E (Bors 2006 eq. 26).

    ``E(sigma) = 1/N sum_i sigma^2 / D(V_i)`` over the N sites (vertices with at least one
    neighbour), hence ``sigma = sqrt(E / mean_i(1 / D(V_i)))``.
    """
    d = ring_distance(vertices, faces)
    d = d[d > 0]
    if d.size == 0:
        return 0.0
    return float(np.sqrt(e / np.mean(1.0 / d)))


def gaussian_noise(vertices, faces, level, rng):
    """Gaussian vertex displacement at normalized displacement E = ``level`` (Bors 2006 eq. 26).

    The paper models ``||V~_i - V_i|| ~ N(0, sigma^2)``: we read this literally, every vertex moves
    along an independent uniformly random direction by a length drawn from N(0, sigma^2), so that
    ``E||V~_i - V_i||^2 = sigma^2`` and E is the mean ratio of the squared displacement to D(V_i).
    """
    v = np.asarray(vertices, np.float64)
    sigma = gaussian_sigma(v, faces, float(level))
    length = rng.normal(0.0, sigma, len(v))
    return v + random_unit_vectors(rng, len(v)) * length[:, None], np.array(faces, np.int64)


def laplacian_smoothing(vertices, faces, level, rng, lam: float = 0.1):
    """``level`` iterations of uniform-weight Laplacian smoothing ``V += lam (mean(N(V)) - V)``,
    lam = 0.1, all vertices (boundary included); isolated vertices stay."""
    v = np.asarray(vertices, np.float64).copy()
    adj = adjacency_matrix(faces, len(v))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    has = deg > 0
    inv = np.zeros_like(deg)
    inv[has] = 1.0 / deg[has]
    walk = sp.diags(inv) @ adj
    for _ in range(int(level)):
        v = v + lam * (walk @ v - v) * has[:, None]
    return v, np.array(faces, np.int64)


def quantize(vertices, faces, level, rng):
    """Quantise coordinates to ``level`` bits on a cubic grid over the bounding box: step = largest
    extent / (2**bits - 1), origin at the box minimum (as mesh compressors such as Draco do)."""
    v = np.asarray(vertices, np.float64)
    lo = v.min(axis=0)
    step = float((v.max(axis=0) - lo).max()) / (2 ** int(level) - 1)
    if step == 0:
        return v.copy(), np.array(faces, np.int64)
    return lo + np.round((v - lo) / step) * step, np.array(faces, np.int64)


def quantization_step(vertices, bits: int) -> float:
    v = np.asarray(vertices, np.float64)
    return float((v.max(axis=0) - v.min(axis=0)).max()) / (2 ** int(bits) - 1)


def simplify(vertices, faces, level, rng):
    """Edge-collapse simplification (fast-simplification, quadric error) removing the fraction
    ``level`` of the faces.  Deterministic; ``rng`` is unused."""
    import fast_simplification

    v = np.ascontiguousarray(vertices, np.float64)
    f = np.ascontiguousarray(faces, np.int32)
    v2, f2 = fast_simplification.simplify(v, f, target_reduction=float(level))
    return drop_unreferenced(np.asarray(v2, np.float64), np.asarray(f2, np.int64))


def simplify_meshopt(vertices, faces, level, rng):
    """meshoptimizer's simplifier (what ``gltf-transform optimize`` and gltfpack ``-si`` run):
    removes the fraction ``level`` of the faces by edge collapses onto existing vertices, which
    keep their positions (error bound 5 % of the mesh extent, so the target is reached).
    Deterministic; ``rng`` is unused."""
    import meshoptimizer

    idx = np.ascontiguousarray(faces, np.uint32).ravel()
    out = np.zeros_like(idx)
    target = int(len(idx) * (1.0 - float(level))) // 3 * 3
    n = meshoptimizer.simplify(out, idx, np.ascontiguousarray(vertices, np.float32),
                               target_index_count=target, target_error=0.05)
    return drop_unreferenced(np.asarray(vertices, np.float64), out[:n].reshape(-1, 3).astype(np.int64))


def subdivide(vertices, faces, level, rng):
    """One step of subdivision: ``level`` = ``"midpoint"`` (trimesh.remesh.subdivide: a vertex on
    every edge, originals kept), ``"sqrt3"`` (:func:`sqrt3_subdivide`: Kobbelt's scheme) or
    ``"loop"`` (trimesh.remesh.subdivide_loop: Loop's scheme, which also moves the original
    vertices)."""
    from trimesh import remesh

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if level == "midpoint":
        v2, f2 = remesh.subdivide(v, f)
    elif level == "sqrt3":
        v2, f2 = sqrt3_subdivide(*drop_unreferenced(v, f))
    elif level == "loop":
        v, f = drop_unreferenced(v, f)  # Loop's weights divide by the valence
        with np.errstate(divide="ignore", invalid="ignore"):
            v2, f2 = remesh.subdivide_loop(v, f, iterations=1)
    else:
        raise ValueError(f"unknown subdivision {level!r}")
    return np.asarray(v2, np.float64), np.asarray(f2, np.int64)


def crop(vertices, faces, level, rng):
    """Remove the fraction ``level`` of the faces with a plane cut along a random direction: faces
    whose centroid projects below the ``level`` quantile are removed, unreferenced vertices dropped."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    d = random_unit_vectors(rng, 1)[0]
    s = v[f].mean(axis=1) @ d
    keep = s >= np.quantile(s, float(level))
    return drop_unreferenced(v, f[keep])


def keep_piece(vertices, faces, fraction: float, rng):
    """A plane-cut piece holding ``fraction`` of the faces (crop of ``1 - fraction``)."""
    return crop(vertices, faces, 1.0 - float(fraction), rng)


# ---------------------------------------------------------------------------------------------
# file round trips (trimesh's writers: what another tool would do to the file)

ROUNDTRIP_FORMATS = ("obj", "ply", "stl", "off", "glb")


def _scene(parts: list[tuple[np.ndarray, np.ndarray]], names: list[str] | None = None):
    import trimesh

    scene = trimesh.Scene()
    for k, (v, f) in enumerate(parts):
        name = names[k] if names else f"part{k}"
        mesh = trimesh.Trimesh(np.asarray(v, np.float64), np.asarray(f, np.int64), process=False)
        scene.add_geometry(mesh, geom_name=name, node_name=name)
    return scene


def export_bytes(vertices, faces, fmt: str, parts=None) -> tuple[bytes, str]:
    """The mesh written by trimesh's exporter for ``fmt``: OBJ (8 significant digits), PLY (binary,
    float32), STL (binary, float32, 3 corners per facet), OFF (10 digits) or GLB (float32).
    With several ``parts`` a trimesh Scene is exported (one mesh per part; formats without a notion
    of several meshes get them concatenated).  Returns the bytes and a file name."""
    import trimesh

    if parts is not None and len(parts) > 1:
        data = _scene(parts).export(file_type=fmt)
    else:
        mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
        data = mesh.export(file_type=fmt)
    if isinstance(data, str):
        data = data.encode("utf-8")
    return bytes(data), f"roundtrip.{fmt}"


def format_roundtrip(vertices, faces, level, rng):
    """Write with trimesh as format ``level`` and read back with the engine's reader (welded)."""
    from core.formats import read_mesh

    data, name = export_bytes(vertices, faces, str(level))
    doc = read_mesh(data, name)
    vs, fs, off = [], [], 0
    for p in doc.parts:
        vs.append(p.vertices)
        fs.append(p.faces + off)
        off += len(p.vertices)
    return np.concatenate(vs), np.concatenate(fs)


def trimesh_roundtrip(vertices, faces, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """Round trip through trimesh only (export then load), for tests without the engine."""
    import trimesh

    data, _ = export_bytes(vertices, faces, fmt)
    m = trimesh.load(io.BytesIO(data), file_type=fmt, force="mesh", process=False)
    m.merge_vertices()
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


# ---------------------------------------------------------------------------------------------
# files with several meshes

#: attacks that keep the vertex count and the faces: run on all parts merged (one global noise level,
#: bounding box or transform), then split back by vertex ranges
KEEPS_TOPOLOGY = frozenset({"none", "similarity", "uniform_noise", "gaussian_noise", "smoothing", "quantize"})


def attack_parts(name: str, parts: list[tuple[np.ndarray, np.ndarray]], level, rng: np.random.Generator):
    """Apply attack ``name`` to a file's meshes, keeping them separate meshes.

    Topology-keeping attacks run once on the merged arrays; the others (reorder, simplify,
    subdivide, crop) run on each mesh with generators seeded alike (a crop cuts every mesh along the
    same direction, removing the same fraction of each).  Returns a list of (V, F) per part.
    """
    fn = ATTACKS[name].function
    if len(parts) == 1:
        return [fn(parts[0][0], parts[0][1], level, rng)]
    if name in KEEPS_TOPOLOGY:
        sizes = [len(v) for v, _ in parts]
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        v = np.concatenate([np.asarray(p[0], np.float64) for p in parts])
        f = np.concatenate([np.asarray(p[1], np.int64) + offsets[k] for k, p in enumerate(parts)])
        v2, _ = fn(v, f, level, rng)
        return [(v2[offsets[k] : offsets[k + 1]], np.array(parts[k][1], np.int64)) for k in range(len(parts))]
    seed = int(rng.integers(1 << 62))
    return [fn(v, f, level, np.random.default_rng(seed)) for v, f in parts]


def write_parts(
    parts: list[tuple[np.ndarray, np.ndarray]], names: list[str] | None = None
) -> tuple[bytes, str]:
    """Attacked mesh as a file: one mesh -> binary PLY with double coordinates (nothing added);
    several -> GLB with one mesh per part (float32), the only written format here whose reader
    keeps meshes apart (the engine embeds each part on its own)."""
    if len(parts) == 1:
        from bench.common import write_ply_double

        return write_ply_double(*parts[0]), "attacked.ply"
    return bytes(_scene(parts, names).export(file_type="glb")), "attacked.glb"


# ---------------------------------------------------------------------------------------------
# the attack grid


@dataclass(frozen=True)
class AttackSpec:
    name: str
    function: Attack
    levels: tuple[Any, ...]
    quick_levels: tuple[Any, ...]
    unit: str  # axis label of the level
    random: bool  # draws from rng (several seeds per level are meaningful)
    title: str

    def label(self, level: Any) -> str:
        if self.name == "uniform_noise":
            return f"{100 * float(level):g} %"
        if self.name == "crop":
            return f"{100 * float(level):g} % removed"
        if self.name in ("simplify", "simplify_meshopt"):
            return f"{100 * float(level):g} % faces removed"
        if self.name in ("similarity", "reorder", "none"):
            return "random" if self.random and self.name != "none" else "-"
        if self.name == "quantize":
            return f"{level} bits"
        if self.name == "smoothing":
            return f"{level} iterations"
        if self.name == "gaussian_noise":
            return f"E = {level:g}"
        return str(level)


ATTACKS: dict[str, AttackSpec] = {
    a.name: a
    for a in [
        AttackSpec("none", none, (0,), (0,), "-", False, "No attack (rewritten as double PLY)"),
        AttackSpec("similarity", similarity, (1,), (1,), "-", True, "Similarity transform"),
        AttackSpec("reorder", reorder, (1,), (1,), "-", True, "Vertex and face re-ordering"),
        AttackSpec(
            "uniform_noise",
            uniform_noise,
            (0.0005, 0.001, 0.003, 0.005),
            (0.0005, 0.003),
            "noise amplitude A (fraction of mean centroid distance)",
            True,
            "Additive uniform noise",
        ),
        AttackSpec(
            "gaussian_noise",
            gaussian_noise,
            (0.001, 0.003, 0.01, 0.03, 0.15),
            (0.003, 0.03),
            "normalized displacement E (eq. 26)",
            True,
            "Gaussian noise (Bors eq. 26)",
        ),
        AttackSpec(
            "smoothing",
            laplacian_smoothing,
            (5, 10, 30, 50),
            (5, 30),
            "Laplacian iterations (lambda = 0.1)",
            False,
            "Laplacian smoothing",
        ),
        AttackSpec(
            "quantize",
            quantize,
            (11, 10, 9, 8, 7),
            (10, 8),
            "bits per coordinate",
            False,
            "Coordinate quantisation",
        ),
        AttackSpec(
            "simplify",
            simplify,
            (0.1, 0.3, 0.5, 0.7),
            (0.1, 0.5),
            "fraction of faces removed",
            False,
            "Simplification (edge collapse)",
        ),
        AttackSpec(
            "simplify_meshopt",
            simplify_meshopt,
            (0.02, 0.05, 0.1, 0.3),
            (0.05,),
            "fraction of faces removed",
            False,
            "Simplification (meshoptimizer, vertices kept in place)",
        ),
        AttackSpec(
            "subdivide",
            subdivide,
            ("midpoint", "loop"),
            ("midpoint",),
            "scheme",
            False,
            "One step of subdivision",
        ),
        AttackSpec(
            "crop",
            crop,
            (0.1, 0.3, 0.5, 0.75),
            (0.1, 0.5),
            "fraction of faces removed",
            True,
            "Cropping by a plane cut",
        ),
        AttackSpec(
            "roundtrip",
            format_roundtrip,
            ROUNDTRIP_FORMATS,
            ("obj", "stl"),
            "format",
            False,
            "File round trip through trimesh's writers",
        ),
    ]
}
