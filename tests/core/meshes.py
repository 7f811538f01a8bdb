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
