"""Every format on the named tiny meshes, and the registry that names the formats.

Each tiny mesh, written in each format and encoding (``helpers.WRITERS``), must be recognised by its
own format, read back as the same triangles, written back unchanged when nothing moved, and, when
one vertex moves, change only that vertex's stored coordinates.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.errors import UnsupportedFormatError
from core.formats import FORMATS, FormatSpec, detect_format, read_mesh, spoken_list
from tests.core.formats.helpers import TINY, WRITERS, TinyMesh, binary_stl

CASES = [pytest.param(fmt, enc, mesh, id=f"{fmt}-{enc}-{mesh.name}")
         for (fmt, enc) in WRITERS for mesh in TINY]


def _file(fmt: str, encoding: str, mesh: TinyMesh) -> tuple[bytes, str]:
    return WRITERS[fmt, encoding](mesh), f"{mesh.name}.{FORMATS[fmt].extension}"


@pytest.mark.parametrize(("fmt", "encoding", "mesh"), CASES)
def test_tiny_mesh_reads_as_written(fmt: str, encoding: str, mesh: TinyMesh) -> None:
    data, name = _file(fmt, encoding, mesh)
    assert detect_format(data, name) == fmt
    doc = read_mesh(data, name)
    assert (doc.format, doc.encoding, len(doc.parts)) == (fmt, encoding, 1)
    part = doc.parts[0]
    assert len(part.vertices) == len(mesh.vertices)  # STL's three corners per facet are welded
    assert TinyMesh("read", part.vertices, part.faces).triangles() == mesh.triangles()
    assert doc.write([part.vertices.copy()]) == data  # nothing moved: the same bytes


@pytest.mark.parametrize(("fmt", "encoding", "mesh"), CASES)
def test_moving_one_vertex_rewrites_only_its_coordinates(fmt: str, encoding: str, mesh: TinyMesh) -> None:
    data, name = _file(fmt, encoding, mesh)
    doc = read_mesh(data, name)
    part = doc.parts[0]
    new = part.vertices.copy()
    new[0] += [0.25, -0.5, 0.125]
    out = doc.write([new])
    again = read_mesh(out, name).parts[0]
    assert np.array_equal(again.vertices[again.slot_to_vertex], doc.quantize(new)[part.slot_to_vertex])
    assert np.array_equal(again.faces, part.faces)
    # binary: the file keeps its size and only 4 bytes per coordinate change (a GLB also rewrites
    # the POSITION accessor's min/max in its JSON chunk, which may change its length)
    if encoding != "ascii" and fmt != "glb":
        changed = np.frombuffer(data, np.uint8) != np.frombuffer(out, np.uint8)
        slots = int(np.count_nonzero(part.slot_to_vertex == 0))
        assert len(out) == len(data) and 0 < changed.sum() <= 12 * slots


def test_every_spec_is_consistent() -> None:
    assert all(isinstance(spec, FormatSpec) and spec.name == name for name, spec in FORMATS.items())
    extensions = [ext for spec in FORMATS.values() for ext in spec.extensions]
    assert len(extensions) == len(set(extensions)) and all(ext == ext.lower() for ext in extensions)
    assert {fmt for fmt, _ in WRITERS} == set(FORMATS)  # a writer for every format


def test_each_tiny_file_is_sniffed_only_by_its_format_or_a_looser_one() -> None:
    """A format's sniffer accepts no file of a format sniffed before it (``sniff_rank``); only the
    looser, later ones may (an ASCII STL also looks like a list of statements to nobody else)."""
    for (fmt, encoding), write in WRITERS.items():
        data = write(TINY[0])
        own = FORMATS[fmt]
        for spec in FORMATS.values():
            if spec is not own and spec.sniff(data, spec.name):
                assert spec.sniff_rank > own.sniff_rank, (fmt, encoding, spec.name)


def test_refusals_name_the_formats_and_the_contradiction() -> None:
    # an extension no format has is not echoed (the caller chose it; nothing the caller sent is)
    with pytest.raises(UnsupportedFormatError, match=r"^unsupported format: this file is not "
                       r"OBJ, PLY, STL, OFF, glTF/GLB or 3DS$"):
        detect_format(b"hello", "notes.txt")
    with pytest.raises(UnsupportedFormatError, match=r"^unsupported format: this file is not OBJ"):
        detect_format(b"hello")
    data, _ = _file("ply", "ascii", TINY[0])
    with pytest.raises(UnsupportedFormatError, match=r"^file name says '\.obj' but the content is PLY$"):
        detect_format(data, "x.obj")
    assert detect_format(data, "x.unknown") == "ply"  # an extension no format claims is not checked


def test_a_binary_stl_of_the_wrong_size_says_what_size_it_declares() -> None:
    data = binary_stl(TINY[0].vertices[TINY[0].faces]) + b"\0"
    with pytest.raises(UnsupportedFormatError, match=r"declares 4 facets, 284 bytes, but has 285\)$"):
        detect_format(data, "x.stl")


def test_spoken_list() -> None:
    assert [spoken_list(w) for w in (["a"], ["a", "b"], ["a", "b", "c"])] == ["a", "a or b", "a, b or c"]
