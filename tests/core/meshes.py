"""Meshes made in code for the engine tests: irregular closed surfaces, and similarity transforms
with re-ordering (what the engine must not notice)."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull


def irregular_sphere(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of random points on a bumpy sphere: an irregular closed triangle mesh."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    hull = ConvexHull(p)
    f = hull.simplices.copy()
    # orient outwards
    c = p[f].mean(axis=1)
    normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    flip = (normal * c).sum(axis=1) < 0
    f[flip] = f[flip][:, ::-1]
    r = 1.0 + 0.05 * np.sin(3 * p[:, 0]) * np.cos(2 * p[:, 1])
    return p * r[:, None], f


def similarity(v: np.ndarray, f: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random rotation, uniform scale in [0.05, 20], translation, vertex and face permutation."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    s = float(np.exp(rng.uniform(np.log(0.05), np.log(20))))
    t = rng.normal(size=3) * 10
    perm = rng.permutation(len(v))
    inv = np.argsort(perm)
    v2 = (s * v @ q.T + t)[perm]
    f2 = inv[f][rng.permutation(len(f))]
    return v2, f2


def suggested(message: str) -> dict[str, Any] | None:
    """The method and strength a refusal says the same payload reads back with (``None``: none)."""
    m = re.search(r"reads back with method=(\w+) at strength ([0-9.]+)", message)
    return None if m is None else {"method": m.group(1), "strength": float(m.group(2))}


def sqrt3_subdivide(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """One step of Kobbelt's sqrt(3) subdivision (SIGGRAPH 2000), vectorised.

    A vertex is inserted at every face centroid and joined to the face's corners; every edge
    shared by exactly two faces is then flipped to join the two new vertices, and each original
    interior vertex of valence n is relaxed to ``(1 - a_n) p + a_n mean(1-ring)`` with
    ``a_n = (4 - 2 cos(2 pi / n)) / 9``.  Simplification of the boundary rule: a face's edge that
    is not shared by exactly two faces (boundary or non-manifold) keeps its triangle
    ``(a, b, centroid)`` unflipped and its vertices are not moved (Kobbelt trisects boundary edges
    every second step instead).  A closed manifold mesh of n vertices and m faces gives n + m
    vertices and 3 m faces, with its orientation kept.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    n, m = len(v), len(f)
    centroid = v[f].mean(axis=1)
    # directed half-edges (a -> b) of face k, in the face's orientation
    a = f.ravel()
    b = f[:, [1, 2, 0]].ravel()
    face = np.repeat(np.arange(m), 3)
    key = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.r_[True, ks[1:] != ks[:-1]]
    group = np.cumsum(start) - 1
    count = np.bincount(group)[group]  # faces sharing each half-edge's undirected edge
    pair = count == 2
    # interior edges: the half-edge a -> b of face f1 and b -> a of face f2 give
    # (a, c2, c1) and (c2, b, c1), c = centroid vertex index
    lead = np.flatnonzero(start & pair)
    first, second = order[lead], order[lead + 1]
    good = (a[first] == b[second]) & (b[first] == a[second])  # opposite half-edges (oriented)
    first, second = first[good], second[good]
    c1, c2 = n + face[first], n + face[second]
    ia, ib = a[first], b[first]
    flipped = np.concatenate([np.stack([ia, c2, c1], axis=1), np.stack([c2, ib, c1], axis=1)])
    # every other edge (boundary, non-manifold, inconsistently oriented): (a, b, c) kept
    other = np.ones(len(a), bool)
    other[first] = other[second] = False
    single = np.flatnonzero(other)
    kept = np.stack([a[single], b[single], n + face[single]], axis=1)
    # relax the original vertices whose edges are all flipped ones
    valence = np.bincount(np.concatenate([a, b]), minlength=n) / 2.0  # each edge has two half-edges
    nsum = np.zeros_like(v)
    np.add.at(nsum, a, v[b])  # each neighbour is added once per half-edge direction
    np.add.at(nsum, b, v[a])
    nsum /= 2.0
    on_other = np.zeros(n, bool)
    on_other[a[single]] = on_other[b[single]] = True
    move = (valence > 0) & ~on_other
    val = np.where(valence > 0, valence, 1.0)
    alpha = (4.0 - 2.0 * np.cos(2.0 * np.pi / val)) / 9.0
    v_new = v.copy()
    v_new[move] = (1.0 - alpha[move, None]) * v[move] + alpha[move, None] * nsum[move] / val[move, None]
    return np.concatenate([v_new, centroid]), np.concatenate([flipped, kept]).astype(np.int64)
