"""The two synchronisation layers end to end: which one reads what (issue 14).

The connectivity layer survives crops (the surface's frame moves), the geometric layer survives
re-triangulation (the connectivity labels are gone); an untouched file reads with the first.
"""

from __future__ import annotations

import meshoptimizer
import numpy as np
import pytest

from core.api import detect_mesh, embed_mesh
from tests.core.meshes import irregular_sphere, similarity

PAYLOAD = "10110011100011110000101011001010"
KEY = "two layers"


def _drop_unreferenced(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


def _simplified(v: np.ndarray, f: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """meshoptimizer's simplifier (what ``gltf-transform optimize`` runs): ``fraction`` of the faces
    removed by edge collapses onto existing vertices."""
    idx = np.ascontiguousarray(f, np.uint32).ravel()
    out = np.zeros_like(idx)
    target = int(len(idx) * (1.0 - fraction)) // 3 * 3
    n = meshoptimizer.simplify(out, idx, np.ascontiguousarray(v, np.float32), target_index_count=target,
                               target_error=0.05)
    return _drop_unreferenced(v, out[:n].reshape(-1, 3).astype(np.int64))


@pytest.fixture(scope="module")
def marked() -> tuple[np.ndarray, np.ndarray, object]:
    """An irregular closed surface of 20,000 vertices with three distinct principal axes and a
    lopsided bump (third moments far from 0), marked with planes."""
    v, f = irregular_sphere(20000, 7)
    v = v * np.array([1.6, 1.0, 0.7]) + 0.3 * np.exp(-8.0 * ((v - [0.8, 0.3, 0.0]) ** 2).sum(axis=1))[:, None]
    new, report = embed_mesh(v, f, KEY, payload=PAYLOAD, method="planes")
    return new, f, report


def test_both_layers_read_the_untouched_mesh(marked) -> None:
    v, f, report = marked
    assert report.layers == ["connectivity", "geometry"] and report.geometric_carriers > 0
    assert report.rms_displacement <= 2e-4
    res = detect_mesh([(v, f)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "connectivity"


@pytest.mark.parametrize("fraction", [0.3, 0.5])
def test_a_simplified_mesh_reads_with_the_geometric_layer(marked, fraction: float) -> None:
    """Simplification keeps few connectivity labels (the connectivity view does not read), but the
    vertices nearest the cells' centres are mostly still there; moved, re-ordered and turned, too."""
    v, f, _ = marked
    sv, sf = _simplified(v, f, fraction)
    assert len(sv) < (1.0 - 0.8 * fraction) * len(v)
    res = detect_mesh([(sv, sf)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "geometry"
    assert res.false_positive_probability < 2e-6
    moved = detect_mesh([similarity(sv, sf, np.random.default_rng(3))], KEY)
    assert moved.detected and moved.payload == PAYLOAD
    assert not detect_mesh([(sv, sf)], "another key").detected


def test_a_crop_reads_with_the_connectivity_layer(marked) -> None:
    """Half the surface cut away moves the frame: the geometric carriers are lost, the
    connectivity ones are not."""
    v, f, _ = marked
    keep = v[f].mean(axis=1)[:, 0] < 0.1
    cv, cf = _drop_unreferenced(v, f[keep])
    res = detect_mesh([(cv, cf)], KEY)
    assert res.detected and res.payload == PAYLOAD and res.layer == "connectivity"
