"""The frame of the regular meshes' geometric fallback (core.sync.cell_frame) and the detector's
search over the frames a rotation leaves open (core.pipeline._turned): surfaces of revolution and
symmetric parts, found after any rotation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import core.sync as sync
from core.api import detect_mesh, embed_mesh
from core.formats import read_mesh
from core.mesh import adjacency
from core.sync import CellFrame, cell_frame, vertex_labels
from tests.conftest import shared_mesh_path


def _cylinder(sections: int = 40) -> np.ndarray:
    """Vertices of a closed cylinder: one unique axis, a degenerate pair with ``sections``-fold symmetry."""
    m = trimesh.creation.cylinder(radius=0.5, height=3.0, sections=sections)
    return np.asarray(m.vertices, np.float64)


def _box() -> np.ndarray:
    """Vertices of a subdivided box of three different sides: every third moment 0."""
    m = trimesh.creation.box(extents=(1.0, 2.0, 3.0)).subdivide().subdivide()
    return np.asarray(m.vertices, np.float64)


def _frames(frame: CellFrame) -> list[np.ndarray]:
    return [frame.axes, *frame.others]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), shift=st.floats(-5, 5))
def test_a_rotated_mesh_has_the_embedders_frame_among_the_detectors(seed: int, shift: float) -> None:
    """The embedder's frame, carried by a rotation, is one that the rotated mesh's detector tries
    (right-handed rotations: the frames are)."""
    rot = Rotation.random(random_state=seed).as_matrix()
    for v in (_cylinder(), _box()):
        before = cell_frame(v)
        after = cell_frame(v @ rot.T + shift)
        want = before.axes @ rot.T
        assert any(np.allclose(c, want, atol=1e-6) for c in _frames(after))
        assert np.allclose(after.origin, before.origin @ rot.T + shift)
        assert after.unit == pytest.approx(before.unit)


def test_candidate_frames_are_the_turns_signs_and_the_file_axes() -> None:
    # the cylinder: 40 turns x 2 signs of its axis (no third moment along it), and the file's axes
    cyl = cell_frame(_cylinder(40))
    assert len(cyl.others) == 40 * 2 - 1 + 1
    assert any(np.array_equal(c, np.eye(3)) for c in cyl.others)
    assert all(np.linalg.det(c) == pytest.approx(1.0) for c in _frames(cyl))
    # the box: three loose signs, the last one fixed by handedness: 4 frames, and the file's axes
    box = cell_frame(_box())
    assert len(box.others) == 3 + 1
    # a part whose third moments fix its axes: one frame, as before the candidates
    v = _box()
    v = v * (1.0 + 0.2 * (v[:, [0]] > 0))  # the +x half wider: an off-centre bulge
    v[:, 1] += 0.3 * (v[:, 1] > 0) * v[:, 1]
    v[:, 2] += 0.4 * (v[:, 2] > 0) * v[:, 2]
    assert cell_frame(v).others == ()
    # a sphere-like vertex cloud (three alike moments): the file's axes alone
    ico = np.asarray(trimesh.creation.icosphere(3).vertices)
    assert np.array_equal(cell_frame(ico).axes, np.eye(3)) and cell_frame(ico).others == ()


def test_the_embedders_turn_does_not_jump_when_carriers_move() -> None:
    # the embedder recomputes the frame after every round of moves: tiny moves keep its turn
    v = _cylinder(40)
    rng = np.random.default_rng(0)
    first = cell_frame(v).axes
    for _ in range(20):
        moved = v + rng.normal(0.0, 1e-5, v.shape)
        assert np.allclose(cell_frame(moved).axes, first, atol=1e-3)


def _capsule() -> tuple[np.ndarray, np.ndarray]:
    name = "capsule.obj"
    part = read_mesh(shared_mesh_path(name).read_bytes(), name).parts[0]
    return part.vertices, part.faces


@pytest.mark.parametrize("method", ["planes", "ellipsoids"])
def test_the_capsule_is_found_after_any_rotation(method: str) -> None:
    """A surface of revolution (regular labels, frame fixed up to its 100 segments' turns and the
    sign of its axis): a 32-bit payload read back after rotations, not with a wrong key."""
    v, f = _capsule()
    assert vertex_labels(v, adjacency(f, len(v))).regular
    payload = "10110011100011110000101011001101"
    marked, _ = embed_mesh(v, f, "capsule-key", payload=payload, method=method)
    plain = detect_mesh([(marked, f)], "capsule-key")
    assert plain.detected and plain.payload == payload and plain.layer == "connectivity"
    for seed in (3, 4):
        rot = Rotation.random(random_state=seed).as_matrix()
        moved = marked @ rot.T + np.array([1.0, -2.0, 0.5])
        res = detect_mesh([(moved, f)], "capsule-key")
        assert res.detected and res.payload == payload, (seed, res)
    wrong = detect_mesh([(marked @ Rotation.random(random_state=5).as_matrix().T, f)], "another-key")
    assert not wrong.detected


def test_a_file_marked_in_the_file_axes_still_reads(monkeypatch) -> None:
    """What the fallback did for every such mesh before the candidates (the file's axes): a file
    marked then reads through the detector's other frames."""
    v, f = _capsule()

    def old(vertices: np.ndarray) -> CellFrame:
        c = vertices.mean(axis=0)
        r = float(np.sqrt(((vertices - c) ** 2).sum(axis=1).mean()))
        return CellFrame(c, r, np.eye(3))

    with monkeypatch.context() as m:
        m.setattr(sync, "cell_frame", old)
        marked, _ = embed_mesh(v, f, "old-key", method="planes")
        assert detect_mesh([(marked, f)], "old-key").detected
    res = detect_mesh([(marked, f)], "old-key")
    assert res.detected and res.layer == "connectivity"


def test_a_unique_axis_along_the_reference_direction_still_gets_a_frame() -> None:
    # the turns are counted from FRAME_REFERENCE projected across the unique axis: along it, a file axis
    v = _cylinder(40)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, sync.FRAME_REFERENCE)
    angle = np.arccos(z @ sync.FRAME_REFERENCE)
    rot = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    frame = cell_frame(v @ rot.T)
    assert np.all(np.isfinite(frame.axes)) and len(frame.others) == 80
    assert any(np.allclose(c, cell_frame(v).axes @ rot.T, atol=1e-6) for c in _frames(frame))
