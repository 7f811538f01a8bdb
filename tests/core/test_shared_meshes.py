"""The engine on every shared real mesh: exact round trips, invariance, Table I, no false positives."""

from __future__ import annotations

import numpy as np
import pytest

from core.api import capacity_file, detect_file, detect_mesh, embed_file
from core.coding import key_code
from core.formats import read_mesh
from tests.conftest import SHARED_MESHES, shared_mesh_path
from tests.core.meshes import similarity

METHODS = ["ellipsoids", "planes"]
PAYLOAD64 = "1100101011110000101001011100001111001010111100001010010111000011"


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", SHARED_MESHES)
def test_round_trip_exact_and_invariant(name: str, method: str) -> None:
    """64 bits where capacity allows (else the key-derived code): 0 errors on the stego file,
    after a similarity transform with permutations, and with float32 positions."""
    data = shared_mesh_path(name).read_bytes()
    cap = capacity_file(data, filename=name, method=method)
    payload = PAYLOAD64 if cap.max_payload_bits >= 64 else None
    if payload is None and cap.carriers < 1.5 * cap.codeword_bits_default:
        pytest.skip(f"{name}: {cap.carriers} carriers, too few even for the 32-bit key code")
    key = f"shared-{name}"
    marked = embed_file(data, key, filename=name, payload=payload, method=method)
    assert marked.format == read_mesh(data, name).format
    expected = payload or "".join(map(str, key_code(key)))
    res = detect_file(marked.data, key, filename=name)
    assert res.detected, res
    assert res.payload == expected and res.method == method
    assert res.key_derived == (payload is None)
    if payload is not None:
        checked = detect_file(marked.data, key, filename=name, payload=payload)
        assert checked.bit_errors == 0 and checked.p_value is not None and checked.p_value < 1e-15
    doc = read_mesh(marked.data, name)
    rng = np.random.default_rng(len(name))
    moved = [similarity(p.vertices, p.faces, rng) for p in doc.parts]
    moved = [(v.astype(np.float32).astype(np.float64), f) for v, f in moved]
    res2 = detect_mesh(moved, key)
    assert res2.detected and res2.payload == expected


def test_sink_carries_the_papers_code() -> None:
    """Table I on the paper's own 'Sink' (674 vertices, 1,068 faces): paper 98 carriers / 2 copies
    with ellipsoids, 66 / 1 with planes."""
    data = shared_mesh_path("sink.3ds").read_bytes()
    for method in METHODS:
        marked = embed_file(data, "sink", filename="sink.3ds", method=method)
        assert marked.report.key_derived and marked.report.codeword_bits == 56
        assert marked.report.copies >= 1.0
        res = detect_file(marked.data, "sink", filename="sink.3ds")
        assert res.detected and res.key_derived and res.bit_errors == 0


def test_each_mesh_of_a_multi_mesh_file_decodes_alone() -> None:
    data = shared_mesh_path("CesiumMilkTruck.glb").read_bytes()
    marked = embed_file(data, "truck", filename="CesiumMilkTruck.glb")
    doc = read_mesh(marked.data, "CesiumMilkTruck.glb")
    assert detect_mesh([(p.vertices, p.faces) for p in doc.parts], "truck").detected
    alone = [p for p in doc.parts if capacity_file_part(p) >= 1.5 * marked.report.codeword_bits]
    assert alone, marked.report.parts
    for part in alone:
        assert detect_mesh([(part.vertices, part.faces)], "truck").detected


def capacity_file_part(part) -> int:
    """Distinct slot labels of a part's carriers under the test key (what a copy of its own needs)."""
    from core.analysis import analyse

    return int(np.unique(analyse(part.vertices, part.faces, "truck", "ellipsoids").slot_hash).size)


@pytest.mark.slow
def test_no_false_positives_in_1000_trials() -> None:
    """Wrong keys on marked meshes and any key on unmarked meshes: never detected."""
    names = ["monkey.glb", "sink.3ds", "spot.obj", "Duck.glb", "decimated-max.obj", "fandisk.off"]
    meshes = []
    for name in names:
        data = shared_mesh_path(name).read_bytes()
        marked = embed_file(data, "the right key", filename=name)
        for blob in (data, marked.data):
            doc = read_mesh(blob, name)
            meshes.append([(p.vertices, p.faces) for p in doc.parts])
    trials = detections = 0
    worst = 0.0
    for i in range(1000):
        res = detect_mesh(meshes[i % len(meshes)], f"wrong key {i}")
        trials += 1
        detections += res.detected
        worst = max(worst, 1.0 - res.false_positive_probability)
    assert trials == 1000 and detections == 0
