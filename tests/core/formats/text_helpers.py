"""Independent (slow, simple) views of the text/simple formats, to check the readers' work."""

from __future__ import annotations

import re

import numpy as np

from core.formats import MeshDocument, read_mesh

_SPLIT = re.compile(rb"(\s+)")


def vertex_lines(fmt: str, data: bytes) -> list[int]:
    """0-based line index of every stored vertex slot, in file order (text encodings)."""
    lines = data.split(b"\n")
    if fmt == "obj":
        return [i for i, ln in enumerate(lines) if ln.split()[:1] == [b"v"]]
    if fmt == "stl":
        return [i for i, ln in enumerate(lines) if ln.split()[:1] in ([b"vertex"], [b"VERTEX"])]
    if fmt == "ply":
        end = next(i for i, ln in enumerate(lines) if ln.strip() == b"end_header")
        header = b"\n".join(lines[:end]).decode()
        first = header.split("element ")[1].split()
        assert first[0] == "vertex", "test helper expects the vertex element first"
        body = [i for i in range(end + 1, len(lines)) if lines[i].strip()]
        return body[: int(first[1])]
    if fmt == "off":
        content = [i for i, ln in enumerate(lines) if ln.strip() and not ln.strip().startswith(b"#")]
        head = lines[content[0]].split(b"#")[0].split()
        rest = content[1:] if len(head) > 1 else content[2:]
        counts = head[1:] if len(head) > 1 else lines[content[1]].split()
        return rest[: int(counts[0])]
    raise AssertionError(fmt)


def coord_tokens(fmt: str) -> tuple[int, int, int]:
    """Index of the x, y, z tokens on a vertex line (for the simple layouts used in tests)."""
    return (1, 2, 3) if fmt in ("obj", "stl") else (0, 1, 2)


def moved_slot_mask(doc: MeshDocument, moved: np.ndarray) -> np.ndarray:
    part = doc.parts[0]
    flag = np.zeros(len(part.vertices), bool)
    flag[moved] = True
    return flag[part.slot_to_vertex]


def assert_text_diff(old: bytes, new: bytes, changed_lines: set[int], tokens: tuple[int, ...]) -> None:
    """Only ``changed_lines`` differ, and on them only the tokens numbered ``tokens``."""
    a, b = old.split(b"\n"), new.split(b"\n")
    assert len(a) == len(b)
    diff = {i for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y}
    assert diff == changed_lines
    for i in diff:
        pa, pb = _SPLIT.split(a[i]), _SPLIT.split(b[i])
        assert len(pa) == len(pb), (a[i], b[i])
        tok = -1
        for x, y in zip(pa, pb, strict=True):
            is_token = bool(x) and not x.isspace()
            tok += is_token
            if x != y:
                assert is_token and tok in tokens, (a[i], b[i])


def ply_vertex_layout(data: bytes) -> tuple[int, int, list[int], int]:
    """(body offset, record size, x/y/z byte offsets in the record, coordinate size) of a binary
    PLY whose first element is a fixed-size vertex element."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    sizes = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
             "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
             "double": 8, "float64": 8}
    offs: dict[str, tuple[int, int]] = {}
    size = 0
    in_vertex = False
    for line in data[:end].decode("latin-1").splitlines():
        t = line.split()
        if t[:1] == ["element"]:
            in_vertex = t[1] == "vertex"
            if not in_vertex and size:
                break
        elif t[:1] == ["property"] and in_vertex:
            assert t[1] != "list"
            offs[t[2]] = (size, sizes[t[1]])
            size += sizes[t[1]]
    return end, size, [offs[c][0] for c in "xyz"], offs["x"][1]


def allowed_binary_bytes(fmt: str, data: bytes, slots: np.ndarray) -> np.ndarray:
    """Byte offsets of the coordinates of the given stored slots (binary PLY / STL)."""
    if fmt == "stl":
        base = 84 + 50 * (slots // 3) + 12 + 12 * (slots % 3)
        return (base[:, None] + np.arange(12)).ravel()
    body, rec, xyz, size = ply_vertex_layout(data)
    base = body + rec * slots
    return (base[:, None, None] + np.array(xyz)[None, :, None] + np.arange(size)).ravel()


def move_some(doc: MeshDocument, fraction: float = 0.01, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """New positions with about ``fraction`` of the vertices moved by ~1e-3 of the bbox diagonal."""
    v = doc.parts[0].vertices
    rng = np.random.default_rng(seed)
    n = max(1, round(len(v) * fraction))
    sel = np.sort(rng.choice(len(v), n, replace=False))
    diag = float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0
    new = v.copy()
    new[sel] += rng.uniform(0.2e-3, 1e-3, (n, 3)) * diag * rng.choice([-1, 1], (n, 3))
    return new, sel


def reread(data: bytes, name: str) -> MeshDocument:
    return read_mesh(data, filename=name)
