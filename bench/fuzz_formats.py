"""Fuzz run of ``core.formats`` over mutated real files (issue 2).

``python -m bench fuzz-formats [--cases 10000] [--seed 2006] [--jobs 2] [--timeout 5]``

Every mesh file of the shared set is mutated in one of five ways (chosen per case):

- ``flip``: 1-16 bytes XORed with random non-zero values (half the time inside the first 4 KiB,
  where the headers live);
- ``truncate``: the file cut at a random byte (half the time inside the first 4 KiB);
- ``insert``: 1-64 random bytes, or a token (``nan``, ``-1``, ``4000000000``, ``\\n``, ``//``,
  a PLY header line...), inserted at a random byte;
- ``duplicate``: a random chunk (1 byte to 64 KiB) copied to another random place;
- ``header``: a format-aware edit of one header field: PLY header counts, types, format line
  and lines; OBJ/OFF numbers (counts, indices, coordinates); binary STL facet count; GLB header
  and chunk lengths or one JSON member (an accessor count, offset, stride, component type,
  buffer index, mode, URI...) set to a hostile value or removed, with the chunk lengths fixed
  up or not; 3DS chunk ids, lengths and vertex/face counts.

Each case is ``core.formats.read_mesh(data, name)``; when the file parses, 20 % of each part's
vertices are moved (scaled by 1 - 1e-5, as small as a watermark) and the document written and
read back: the same parts and stored slots must come back, every slot at ``doc.quantize`` of
its new position (see :func:`_compare`).  Cases run in ``--jobs`` worker processes; the parent
gives each case ``--timeout`` seconds (default 5), then kills the worker, records a hang and
starts a new one.  Workers run under an address-space limit, so a runaway allocation shows as
a ``MemoryError`` finding instead of swapping.  Only :class:`core.errors.MeshMarkError`
subclasses may escape: anything else, a hang, a crash, or a written file that does not read
back as promised is a finding.  Cases are fixed by ``(seed, case number)``; reproduce one with
``python -m bench.fuzz_formats --case N [--seed S] [--save FILE]``.
"""

from __future__ import annotations

import json
import os
import re
import resource
import select
import struct
import subprocess
import sys
import time
import traceback
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import ROOT, environment, md_table, meshes_dir

MUTATIONS = ("flip", "truncate", "insert", "duplicate", "header")
HEAD = 4096
TOKENS = [
    b"nan", b"-nan", b"inf", b"-1", b"0", b"-0", b"1e999", b"4000000000", b"18446744073709551616",
    b"1.5", b"255", b"/", b"//", b"/1/", b"\r\n", b"\n", b"\r", b" ", b"\t", b"#", b"\x00", b"\xff",
    b"f ", b"v ", b"f 1 2 3\n", b"f 0 0 0\n", b"f -9 1 2\n", b"v 1 2\n", b"v nan 0 0\n", b"o x\n",
    b"end_header\n", b"element vertex 4000000000\n", b"element face 3\n", b"property float x\n",
    b"property list uchar int vertex_indices\n", b"format ascii 1.0\n", b"comment \xff\n",
    b"OFF\n", b"3 0 1 2\n", b"4000000000 1 0\n", b"solid ", b"facet normal 0 0 0\n", b"endloop",
    b"glTF", b"JSON", b"BIN\x00", b'"accessors"', b'{"a":', b"[[[[[[[[", b"\\u0000", b"data:",
]
INTERESTING_INTS = [
    0, 1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 13, 255, 256, 65535, 65536, 2**31 - 1, 2**31, 2**32 - 1,
    2**32, 2**53 + 1, 2**63 - 1, 2**63, 2**64, -1, -2, -(2**31), -(2**63),
]
INTERESTING_TEXT = [str(i).encode() for i in INTERESTING_INTS] + [
    b"nan", b"inf", b"-inf", b"1e309", b"-0", b"0.5", b"1.5", b"1e-320", b"", b"x", b"1/2/3", b"-0x1",
    b"1e", b"--1", b"+1", b"1.2.3", b"9" * 40,
]
INTERESTING_JSON: list[Any] = [
    *INTERESTING_INTS, 1.5, -0.0, 1e308, -1e308, None, True, False, "", "x", "VEC3", "SCALAR", "VEC2",
    "data:", "data:application/octet-stream;base64,AAAA", "data:application/octet-stream;base64,!!",
    "file:///etc/passwd", "../x.bin", "http://example.com/x.bin", [], {}, [0, 0, 0], [1e39, 0, 0],
    5120, 5121, 5122, 5123, 5124, 5125, 5126, {"POSITION": 0}, [{"attributes": {}}],
]
PLY_WORDS = [
    b"float", b"double", b"uchar", b"char", b"int", b"uint", b"short", b"ushort", b"int8", b"float64",
    b"list", b"list uchar int", b"list int float", b"list float int", b"vertex", b"face", b"x", b"y",
    b"vertex_indices", b"vertex_index", b"ascii", b"binary_little_endian", b"binary_big_endian",
    b"element", b"property", b"", b"bogus",
]
_NUMBER = re.compile(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_PLY_WORD = re.compile(rb"[A-Za-z_][A-Za-z0-9_]*")


#: findings of earlier runs, fixed since (shown in the report): (run, case, what, fix, regression test)
FIXED = [
    (
        "`--cases 100000 --seed 1`",
        "74204, 74864: `turbineblade.ply`, face list type `int` -> `float64`",
        "hang (1.7 s alone, > 5 s under load): the binary PLY walk spent several numpy calls on every run "
        "of equal list lengths, and the 199,034 records now had random lengths (mixed triangles and quads, "
        "a legitimate file, cost the same ~5 us per face)",
        "`core/formats/ply.py`: runs shorter than 32 records are scanned record by record in batches "
        "(0.1 s here; 100k mixed faces 0.49 -> 0.06 s), and the records of every binary element with a list "
        "count against the faces limit",
        "`tests/core/formats/test_ply_varying_lists.py`",
    ),
    (
        "`--cases 100000 --seed 1`",
        "38980: `rocker-arm.obj`, random bytes glued to a z coordinate (`0.4955#*~...\\r...39`)",
        "the written file did not parse: the reader strips the `#` comment, but the writer's z token ran "
        "to the next whitespace (the `\\r`), so moving that vertex deleted part of the comment",
        "`core/formats/_text.py` `patch_lines`: tokens end at a `#`, as for the readers",
        "`tests/core/formats/test_text_glued_comments.py`",
    ),
    (
        "`--meshes Duck.quantized.glb Duck.meshopt.glb Duck.draco.glb --cases 5000`",
        "1829, 2798, 2963, 4151 (`Duck.draco.glb`, bytes inserted or duplicated in the stream); 1979",
        "MeshFormatError at write, 'Draco re-encoding would not give the marked positions back': the "
        "damaged streams still decoded, with repeated points (edgebreaker merged them when re-encoding) "
        "or, in 1979, coordinates near 6e17 on a 'grid' finer than float32 holds there",
        "`core/formats/gltf.py`, `gltf_codecs.py`: the accessor counts follow the new stream (edgebreaker "
        "merges points equal in every attribute: valid, the same positions, fewer slots; this check then "
        "compares the positions as a set), the result is compared as a set of positions, and no grid "
        "below four float32 spacings is claimed (such positions are never moved)",
        "`tests/core/formats/test_gltf_encodings.py` (`test_draco_stream_with_repeated_points_...`, "
        "`test_draco_grid_refused_where_...`)",
    ),
]


def mesh_files() -> list[Path]:
    """Every mesh of the shared set (README.md, the set's description, is left out), and the
    compressed and quantized GLBs of :func:`encoded_seeds`."""
    shared = sorted(p for p in meshes_dir().iterdir() if p.is_file() and p.suffix.lower() != ".md")
    files = shared + encoded_seeds()
    only = os.environ.get("MESHMARK_FUZZ_ONLY")  # --meshes: those file names only
    return [p for p in files if p.name in only.split(",")] if only else files


def encoded_seeds() -> list[Path]:
    """``Duck.glb`` re-stored as 14-bit USHORT positions (KHR_mesh_quantization), compressed
    with EXT_meshopt_compression and with KHR_draco_mesh_compression: seeds for the decoders.
    Written once, deterministically, next to the other temporary files."""
    import DracoPy
    import meshoptimizer

    from core.formats import read_mesh

    where = Path(os.environ.get("TMPDIR", "/tmp")) / "meshmark-fuzz-seeds"
    names = [where / f"Duck.{k}.glb" for k in ("quantized", "meshopt", "draco")]
    if all(p.is_file() for p in names):
        return names
    where.mkdir(parents=True, exist_ok=True)
    part = read_mesh((meshes_dir() / "Duck.glb").read_bytes(), "Duck.glb").parts[0]
    v, f = part.vertices, part.faces
    q = np.rint((v - v.min(axis=0)) / float(np.ptp(v, axis=0).max()) * 16383).astype("<u2")
    rows = np.zeros((len(v), 8), np.uint8)
    rows[:, :6] = q.view(np.uint8).reshape(len(v), 6)
    idx = f.astype("<u2").tobytes()

    def glb(meta: dict[str, Any], blob: bytes) -> bytes:
        text = json.dumps(meta).encode()
        text += b" " * (-len(text) % 4)
        blob += b"\0" * (-len(blob) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text
        body += struct.pack("<II", len(blob), 0x004E4942) + blob
        return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body

    def accessors(pos_view: int | None, idx_view: int | None) -> list[dict[str, Any]]:
        pos = {"componentType": 5123, "count": len(v), "type": "VEC3", "min": q.min(axis=0).tolist(),
               "max": q.max(axis=0).tolist()}
        ind = {"componentType": 5123, "count": f.size, "type": "SCALAR"}
        return [{**pos, **({} if pos_view is None else {"bufferView": pos_view})},
                {**ind, **({} if idx_view is None else {"bufferView": idx_view})}]

    mesh = [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}]
    quant = {"asset": {"version": "2.0"}, "meshes": mesh, "accessors": accessors(0, 1),
             "bufferViews": [{"buffer": 0, "byteLength": rows.nbytes, "byteStride": 8},
                             {"buffer": 0, "byteOffset": rows.nbytes, "byteLength": len(idx)}],
             "buffers": [{"byteLength": rows.nbytes + len(idx)}]}
    names[0].write_bytes(glb(quant, rows.tobytes() + idx))
    meshoptimizer.encode_vertex_version(0)
    meshoptimizer.encode_index_version(1)
    cpos = meshoptimizer.encode_vertex_buffer(rows, len(v), 8)
    cidx = meshoptimizer.encode_index_buffer(f.astype(np.uint32).ravel(), f.size, len(v))
    at = len(cpos) + (-len(cpos) % 4)
    ext = "EXT_meshopt_compression"
    mo = {"asset": {"version": "2.0"}, "meshes": mesh, "accessors": accessors(0, 1), "bufferViews": [
        {"buffer": 1, "byteLength": rows.nbytes, "byteStride": 8, "extensions": {ext: {
            "buffer": 0, "byteLength": len(cpos), "byteStride": 8, "mode": "ATTRIBUTES", "count": len(v)}}},
        {"buffer": 1, "byteOffset": rows.nbytes, "byteLength": len(idx), "extensions": {ext: {
            "buffer": 0, "byteOffset": at, "byteLength": len(cidx), "byteStride": 2, "mode": "TRIANGLES",
            "count": f.size}}}],
        "buffers": [{"byteLength": at + len(cidx)},
                    {"byteLength": rows.nbytes + len(idx), "extensions": {ext: {"fallback": True}}}]}
    names[1].write_bytes(glb(mo, cpos + b"\0" * (at - len(cpos)) + cidx))
    stream = DracoPy.encode(v.astype(np.float32), f, quantization_bits=14)
    dr = {"asset": {"version": "2.0"}, "meshes": [{"primitives": [{
        "attributes": {"POSITION": 0}, "indices": 1,
        "extensions": {"KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {"POSITION": 0}}}}]}],
        "accessors": [{"componentType": 5126, "count": len(v), "type": "VEC3"},
                      {"componentType": 5123, "count": f.size, "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteLength": len(stream)}], "buffers": [{"byteLength": len(stream)}]}
    names[2].write_bytes(glb(dr, bytes(stream)))
    return names


# ---------------------------------------------------------------------------------------------
# mutations: (data, rng) -> (new data, description)


def _where(n: int, rng: np.random.Generator) -> int:
    """A byte position, half the time inside the first 4 KiB (the headers)."""
    if n <= 0:
        return 0
    return int(rng.integers(0, min(n, HEAD) if rng.random() < 0.5 else n))


def m_flip(data: bytes, rng: np.random.Generator, ext: str) -> tuple[bytes, str]:
    if not data:
        return data, "flip (empty)"
    buf = bytearray(data)
    k = int(rng.integers(1, 17))
    at = [_where(len(buf), rng) for _ in range(k)]
    for i in at:
        buf[i] ^= int(rng.integers(1, 256))
    return bytes(buf), f"flip {k} byte(s) at {sorted(at)[:6]}"


def m_truncate(data: bytes, rng: np.random.Generator, ext: str) -> tuple[bytes, str]:
    i = _where(len(data), rng)
    return data[:i], f"truncate at {i} of {len(data)}"


def m_insert(data: bytes, rng: np.random.Generator, ext: str) -> tuple[bytes, str]:
    i = _where(len(data) + 1, rng)
    if rng.random() < 0.5:
        blob = rng.integers(0, 256, int(rng.integers(1, 65))).astype(np.uint8).tobytes()
        what = f"{len(blob)} random bytes"
    else:
        blob = TOKENS[int(rng.integers(len(TOKENS)))]
        what = repr(blob)
    return data[:i] + blob + data[i:], f"insert {what} at {i}"


def m_duplicate(data: bytes, rng: np.random.Generator, ext: str) -> tuple[bytes, str]:
    if not data:
        return data, "duplicate (empty)"
    size = int(min(len(data), 2 ** rng.uniform(0, 16)))
    a = int(rng.integers(0, len(data) - size + 1))
    b = _where(len(data) + 1, rng)
    return data[:b] + data[a : a + size] + data[b:], f"duplicate {size} bytes from {a} to {b}"


def _replace_number(data: bytes, rng: np.random.Generator, lo: int, hi: int) -> tuple[bytes, str]:
    """Replace one number token found in ``data[lo:hi]`` by a hostile value."""
    tokens = list(_NUMBER.finditer(data, lo, hi))
    if not tokens:
        return m_flip(data, rng, "")
    t = tokens[int(rng.integers(len(tokens)))]
    old = t.group()
    if rng.random() < 0.7:
        new = INTERESTING_TEXT[int(rng.integers(len(INTERESTING_TEXT)))]
    else:  # a near miss of the true value
        try:
            v = int(old)
            new = str(v + int(rng.choice([-1, 1, 2, -2])) if rng.random() < 0.7 else v * 2).encode()
        except ValueError:
            new = old[::-1]
    return data[: t.start()] + new + data[t.end() :], f"number {old[:20]!r} at {t.start()} -> {new[:20]!r}"


def _ply_header(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    end = data.find(b"end_header")
    hi = end if end > 0 else min(len(data), HEAD)
    r = rng.random()
    if r < 0.45:
        return _replace_number(data, rng, 0, hi)
    lines = data[:hi].split(b"\n")
    if r < 0.75:  # a word of the header: type, element or property name, format...
        words = [(k, m) for k, ln in enumerate(lines) for m in _PLY_WORD.finditer(ln)]
        if not words:
            return m_flip(data, rng, "ply")
        k, m = words[int(rng.integers(len(words)))]
        new = PLY_WORDS[int(rng.integers(len(PLY_WORDS)))]
        lines[k] = lines[k][: m.start()] + new + lines[k][m.end() :]
        what = f"header line {k + 1} word {m.group()[:20]!r} -> {new!r}"
    else:  # drop, duplicate or swap header lines
        k = int(rng.integers(1, max(2, len(lines))))
        k = min(k, len(lines) - 1)
        op = ["drop", "duplicate", "swap"][int(rng.integers(3))]
        if op == "drop":
            del lines[k]
        elif op == "duplicate":
            lines.insert(k, lines[k])
        else:
            j = int(rng.integers(1, max(2, len(lines))))
            j = min(j, len(lines) - 1)
            lines[k], lines[j] = lines[j], lines[k]
        what = f"header line {k + 1}: {op}"
    return b"\n".join(lines) + data[hi:], what


def _text_header(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    """OBJ/OFF/ASCII STL: a number near the start (counts) or anywhere (coordinates, indices)."""
    if rng.random() < 0.4:
        return _replace_number(data, rng, 0, min(len(data), 512))
    i = int(rng.integers(0, max(1, len(data))))
    return _replace_number(data, rng, i, min(len(data), i + 256))


def _u32(data: bytes, rng: np.random.Generator, at: int, name: str) -> tuple[bytes, str]:
    if at + 4 > len(data):
        return m_flip(data, rng, "")
    old = struct.unpack_from("<I", data, at)[0]
    choices = [v for v in INTERESTING_INTS if 0 <= v < 2**32] + [old + 1, old - 1, old * 2, len(data) - at]
    v = int(choices[int(rng.integers(len(choices)))]) % 2**32
    return data[:at] + struct.pack("<I", v) + data[at + 4 :], f"{name} {old} -> {v}"


def _json_paths(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [path] if path else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _json_paths(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:64]):
            out += _json_paths(v, (*path, i))
    return out


def _glb_header(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    if len(data) < 20 or rng.random() < 0.25:
        fields = [(4, "version"), (8, "total length"), (12, "JSON chunk length"), (16, "JSON chunk type")]
        if len(data) >= 20:
            jl = struct.unpack_from("<I", data, 12)[0]
            fields += [(20 + jl, "BIN chunk length"), (24 + jl, "BIN chunk type")]
        at, name = fields[int(rng.integers(len(fields)))]
        return _u32(data, rng, at, name)
    jl = struct.unpack_from("<I", data, 12)[0]
    try:
        doc = json.loads(data[20 : 20 + jl])
    except ValueError:
        return m_flip(data, rng, "glb")
    paths = _json_paths(doc)
    if not paths:
        return m_flip(data, rng, "glb")
    path = paths[int(rng.integers(len(paths)))]
    parent = doc
    for p in path[:-1]:
        parent = parent[p]
    r = rng.random()
    if r < 0.15:
        del parent[path[-1]]
        what = "removed"
    elif r < 0.25 and isinstance(parent, list):
        parent.append(parent[path[-1]])
        what = "duplicated"
    else:
        value = INTERESTING_JSON[int(rng.integers(len(INTERESTING_JSON)))]
        parent[path[-1]] = value
        what = f"= {json.dumps(value)[:40]}"
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = data[20 + jl :]
    fix = rng.random() < 0.9
    total = 20 + len(text) + len(rest) if fix else struct.unpack_from("<I", data, 8)[0]
    head = data[:8] + struct.pack("<III", total, len(text) if fix else jl, 0x4E4F534A)
    where = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path)
    return head + text + rest, f"JSON {where} {what}" + ("" if fix else " (lengths not fixed)")


_3DS_CONTAINERS = {0x4D4D, 0x3D3D, 0x4000, 0x4100, 0xB000, 0xAFFF}


def _3ds_chunks(data: bytes, start: int, end: int, depth: int = 0) -> list[tuple[int, int, int]]:
    """(offset, id, length) of the chunks on the path the reader walks."""
    out: list[tuple[int, int, int]] = []
    pos = start
    while pos + 6 <= end and depth < 8:
        cid, length = struct.unpack_from("<HI", data, pos)
        out.append((pos, cid, length))
        if length < 6 or pos + length > end:
            break
        if cid in _3DS_CONTAINERS:
            body = pos + 6
            if cid == 0x4000:
                z = data.find(b"\x00", body, pos + length)
                body = z + 1 if z >= 0 else pos + length
            out += _3ds_chunks(data, body, pos + length, depth + 1)
        pos += length
    return out


def _3ds_header(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    chunks = _3ds_chunks(data, 0, len(data))
    if not chunks:
        return m_flip(data, rng, "3ds")
    at, cid, _ = chunks[int(rng.integers(len(chunks)))]
    r = rng.random()
    if r < 0.5:
        return _u32(data, rng, at + 2, f"chunk 0x{cid:04X} length")
    if r < 0.7:
        ids = [0x4D4D, 0x3D3D, 0x4000, 0x4100, 0x4110, 0x4120, 0x4140, 0x4160, 0x0000, 0xFFFF]
        new = int(rng.choice(ids))
        return data[:at] + struct.pack("<H", new) + data[at + 2 :], f"chunk 0x{cid:04X} id -> 0x{new:04X}"
    count_chunks = [c for c in chunks if c[1] in (0x4110, 0x4120, 0x4140)] or chunks
    at, cid, _length = count_chunks[int(rng.integers(len(count_chunks)))]
    if at + 8 > len(data):
        return m_flip(data, rng, "3ds")
    old = struct.unpack_from("<H", data, at + 6)[0]
    new = int(rng.choice([0, 1, 2, 3, 255, 65535, old + 1, old - 1, old * 2])) % 65536
    return data[: at + 6] + struct.pack("<H", new) + data[at + 8 :], f"chunk 0x{cid:04X} count {old} -> {new}"


def m_header(data: bytes, rng: np.random.Generator, ext: str) -> tuple[bytes, str]:
    if ext == "ply":
        return _ply_header(data, rng)
    if ext in ("obj", "off"):
        return _text_header(data, rng)
    if ext == "glb":
        return _glb_header(data, rng)
    if ext == "3ds":
        return _3ds_header(data, rng)
    if ext == "stl":
        if data[:5].lower() == b"solid" and b"facet" in data[:4096]:
            return _text_header(data, rng)
        return _u32(data, rng, 80, "STL facet count")
    return m_flip(data, rng, ext)


MUTATORS = {"flip": m_flip, "truncate": m_truncate, "insert": m_insert, "duplicate": m_duplicate,
            "header": m_header}


def make_case(seed: int, case: int, files: list[Path], cache: dict[Path, bytes]) -> tuple[str, bytes, str]:
    """(file name, mutated bytes, description) of case ``case``: the same for the same seed."""
    rng = np.random.default_rng([seed, case])
    path = files[case % len(files)]
    if path not in cache:
        cache[path] = path.read_bytes()
    data = cache[path]
    kind = MUTATIONS[int(rng.integers(len(MUTATIONS)))]
    desc = [kind]
    for _ in range(1 if rng.random() < 0.8 else int(rng.integers(2, 4))):  # sometimes stacked
        data, what = MUTATORS[kind](data, rng, path.suffix[1:].lower())
        desc.append(what)
    return path.name, data, "; ".join(desc)


# ---------------------------------------------------------------------------------------------
# one case


def _aliased(doc: Any) -> list[np.ndarray] | None:
    """glTF: per part, the slots whose stored position element other slots use too (written once,
    from the first part using it); ``None`` for the other formats."""
    slots = getattr(doc, "_slots", None)
    if doc.format not in ("glb", "gltf") or slots is None:
        return None
    keys = [(np.asarray(s[0], np.int64) << 40) | np.asarray(s[1], np.int64) for s in slots]
    every = np.concatenate(keys) if keys else np.zeros(0, np.int64)
    unique, counts = np.unique(every, return_counts=True)
    shared = unique[counts > 1]
    return [np.isin(k, shared) for k in keys]


def _compare(doc: Any, new: list[np.ndarray], again: Any) -> str:
    """Outcome of reading back what ``doc.write(new)`` wrote.

    Every stored slot must read back as ``doc.quantize`` of its new position (slots sharing a
    glTF position element with another part excepted: the first part's move wins), with the same
    parts and slots.  The faces may still differ: welding joins equal positions and keeps apart
    coinciding corners of one triangle, so moves on degenerate (mutated) geometry can change
    what welds: that is reported, not a finding.
    """
    if len(again.parts) != len(doc.parts):
        return "finding:parts-changed-after-write"
    aliased = _aliased(doc)
    for i, (p, a, n) in enumerate(zip(doc.parts, again.parts, new, strict=True)):
        if a.slot_to_vertex.shape != p.slot_to_vertex.shape:
            # a re-encoded Draco stream may merge points equal in every attribute (documented):
            # then the positions must be the same set
            want_set = {tuple(r) for r in doc.quantize_part(i, np.arange(len(n)), n).tolist()}
            if getattr(doc, "_draco", None) and {tuple(r) for r in a.vertices.tolist()} == want_set:
                continue
            return "finding:slots-changed-after-write"
        want = doc.quantize_part(i, np.arange(len(n)), n)[p.slot_to_vertex] + 0.0
        got = a.vertices[a.slot_to_vertex] + 0.0
        ok = np.all(want == got, axis=1)
        if aliased is not None:
            ok |= aliased[i]
        if not ok.all():
            return "finding:positions-differ-after-write"
    same = all(np.array_equal(a.faces, p.faces) for p, a in zip(doc.parts, again.parts, strict=True))
    return "parsed" if same else "parsed, welding changed by the moves"


def run_case(name: str, data: bytes) -> dict[str, Any]:
    """Parse, and when that works write moved vertices and read back. Never raises."""
    from core.errors import MeshMarkError
    from core.formats import read_mesh

    out: dict[str, Any] = {"stage": "read"}
    t = time.perf_counter()
    try:
        doc = read_mesh(data, name)
        out["stage"] = "write"
        rng = np.random.default_rng(len(data))
        new = []
        for p in doc.parts:
            v = np.array(p.vertices, dtype=np.float64)
            pick = rng.random(len(v)) < 0.2
            v[pick] = np.where(v[pick] == 0, 1e-5, v[pick] * (1 - 1e-5))
            new.append(v)
        if doc.format in ("glb", "gltf"):  # as the engine does: on each accessor's own grid
            new = [doc.quantize_part(i, np.arange(len(v)), v) for i, v in enumerate(new)]
        written = doc.write(new)
        out["stage"] = "reread"
        again = read_mesh(written, name)
        out["outcome"] = _compare(doc, new, again)
    except MeshMarkError as e:
        out["outcome"] = type(e).__name__
        if out["stage"] != "read":
            out["outcome"] = f"finding:{type(e).__name__}-at-{out['stage']}"
            out["message"] = str(e)[:300]
    except BaseException as e:  # this is what the fuzz run looks for
        out["outcome"] = f"finding:{type(e).__name__}"
        out["message"] = str(e)[:300]
        out["traceback"] = traceback.format_exc()[-2000:]
    out["seconds"] = time.perf_counter() - t
    return out


def worker(seed: int, address_space: int) -> None:
    """Line protocol on stdin/stdout: a case number in, one JSON line out."""
    if address_space > 0:
        resource.setrlimit(resource.RLIMIT_AS, (address_space, address_space))
    import core.formats.gltf  # imports outside the per-case timing
    import core.formats.obj
    import core.formats.off
    import core.formats.ply
    import core.formats.stl
    import core.formats.tds  # noqa: F401

    files = mesh_files()
    cache: dict[Path, bytes] = {}
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    for line in sys.stdin:
        case = int(line)
        name, data, desc = make_case(seed, case, files, cache)
        res = run_case(name, data)
        res.update(case=case, file=name, mutation=desc, size=len(data))
        sys.stdout.write(json.dumps(res) + "\n")
        sys.stdout.flush()


# ---------------------------------------------------------------------------------------------
# orchestration


class _Worker:
    def __init__(self, seed: int, address_space: int) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "bench.fuzz_formats", "--worker", str(seed), str(address_space)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        self.case: int | None = None
        self.started = 0.0
        self.buf = b""
        assert self.proc.stdout is not None
        self.stdout = self.proc.stdout
        # wait for the imports, so that they do not count against the first case's timeout
        ready, _, _ = select.select([self.stdout], [], [], 300)
        if not ready or self.stdout.readline() != b"ready\n":
            self.stop()
            raise RuntimeError("fuzz worker did not start")

    def send(self, case: int) -> None:
        assert self.proc.stdin is not None
        self.case, self.started = case, time.perf_counter()
        self.proc.stdin.write(f"{case}\n".encode())
        self.proc.stdin.flush()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()  # our own child, by its handle
        self.proc.wait()


def _address_space() -> int:
    """Virtual memory allowed to a worker: its idle size plus 3 GiB."""
    probe = subprocess.run(
        [sys.executable, "-c", "import numpy, core.formats.ply; print(open('/proc/self/status').read())"],
        capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    m = re.search(r"VmPeak:\s+(\d+) kB", probe.stdout)
    base = int(m.group(1)) * 1024 if m else 2 * 2**30
    return base + 3 * 2**30


def fuzz(seed: int, cases: int, jobs: int, timeout: float, progress: bool = True) -> dict[str, Any]:
    address_space = _address_space()
    results: list[dict[str, Any]] = []
    pending = list(range(cases))[::-1]
    workers = [_Worker(seed, address_space) for _ in range(max(1, jobs))]
    t0 = time.perf_counter()
    last = t0
    try:
        while pending or any(w.case is not None for w in workers):
            for w in workers:
                if w.case is None and pending:
                    w.send(pending.pop())
            busy = [w for w in workers if w.case is not None]
            fds = [w.stdout for w in busy]
            now = time.perf_counter()
            wait = max(0.0, min(w.started + timeout - now for w in busy))
            ready, _, _ = select.select(fds, [], [], wait)
            now = time.perf_counter()
            for w in busy:
                if w.stdout in ready:
                    chunk = os.read(w.stdout.fileno(), 1 << 16)
                    if not chunk:  # the worker died (crash, or killed by the kernel)
                        code = w.proc.wait()
                        died = {"case": w.case, "outcome": f"finding:worker-died-{code}"}
                        results.append({**died, "seconds": now - w.started})
                        workers[workers.index(w)] = _Worker(seed, address_space)
                        continue
                    w.buf += chunk
                    while b"\n" in w.buf:
                        line, w.buf = w.buf.split(b"\n", 1)
                        results.append(json.loads(line))
                        w.case = None
                elif now - w.started > timeout:
                    results.append({"case": w.case, "outcome": "finding:hang", "seconds": now - w.started})
                    w.stop()
                    workers[workers.index(w)] = _Worker(seed, address_space)
            if progress and now - last > 30:
                last = now
                print(f"  fuzz-formats: {len(results)}/{cases} cases, {now - t0:.0f} s", flush=True)
    finally:
        for w in workers:
            if w.proc.stdin:
                w.proc.stdin.close()
            w.stop()
    files = mesh_files()
    cache: dict[Path, bytes] = {}
    for r in results:  # describe the cases the parent recorded itself (hangs, crashes)
        if "mutation" not in r:
            name, data, desc = make_case(seed, r["case"], files, cache)
            r.update(file=name, mutation=desc, size=len(data))
    results.sort(key=lambda r: r["case"])
    return {"results": results, "elapsed_s": time.perf_counter() - t0, "address_space": address_space}


def run(args: Any) -> dict[str, Any]:
    from bench.formats_speed import run_header, update_report

    load_start = os.getloadavg()
    env = environment()
    cases = int(getattr(args, "cases", 10_000))
    timeout = float(getattr(args, "timeout", 5.0))
    if args.meshes:  # the workers list their files themselves: tell them through the environment
        os.environ["MESHMARK_FUZZ_ONLY"] = ",".join(args.meshes)
    out = fuzz(args.seed, cases, args.jobs, timeout)
    out.update(env=env, load_start=load_start, load_end=os.getloadavg(), seed=args.seed, cases=cases,
               timeout=timeout, jobs=args.jobs, files=[p.name for p in mesh_files()])
    section = "fuzz-encoded" if args.meshes else "fuzz"
    update_report(Path(args.out), section, fuzz_section(out, run_header))
    findings = [r for r in out["results"] if r["outcome"].startswith("finding")]
    print(f"  fuzz-formats: {len(out['results'])} cases, {len(findings)} finding(s)", flush=True)
    return out


def fuzz_section(out: dict[str, Any], run_header: Any) -> str:
    results = out["results"]
    by_outcome = Counter(r["outcome"] for r in results)
    kinds = Counter(r["mutation"].split(";")[0] for r in results)
    findings = [r for r in results if r["outcome"].startswith("finding")]
    slow = sorted(results, key=lambda r: -r["seconds"])[:5]
    title = "mutated real files" if len(out["files"]) > 3 else "quantized and compressed glTF seeds"
    lines = [f"## Fuzzing ({title})", ""]
    lines += run_header(out["env"], out["load_start"], out["load_end"])
    lines += [
        f"- Wall time: {out['elapsed_s'] / 60:.1f} min; {out['jobs']} worker process(es); "
        f"seed {out['seed']}; "
        f"per-case timeout {out['timeout']:g} s (the parent kills the worker and records a hang); workers "
        f"limited to {out['address_space'] / 2**30:.1f} GiB of address space (RLIMIT_AS).",
        f"- Seed files ({len(out['files'])}): " + ", ".join(out["files"]) + ".",
        "- Mutations (one per case, stacked 2-3 times in 20 % of the cases): "
        + ", ".join(f"{k} {v:,}" for k, v in sorted(kinds.items()))
        + ". See the docstring of `bench/fuzz_formats.py` for what each does.",
        "- A case = `read_mesh(mutated, name)`; if it parses, 20 % of the vertices are moved (x (1 - 1e-5)) "
        "and the file written and read back: the same parts and stored slots must come back, each slot at "
        "`doc.quantize(new)` (glTF: the new positions first put on each accessor's grid with "
        "`doc.quantize_part`, as the engine does; slots whose position element another part shares "
        "excepted: the first part's move wins, as documented). *parsed, welding changed by the moves*: "
        "positions as promised, "
        "but welding gives other faces, because the mutated geometry had corners of one triangle at "
        "the same position (kept apart by `weld`) that the moves separate: not a finding.",
        "- Only `core.errors.MeshMarkError` subclasses may escape; any other exception, a hang, a "
        "crashed worker or a file that does not read back as promised is a finding.",
        "",
        f"**Cases run: {len(results):,}. Findings: {len(findings)}.** "
        f"Parsed (and written, and read back): {by_outcome.get('parsed', 0):,}.",
        "",
        md_table(
            ["outcome", "cases"],
            [[k, v] for k, v in sorted(by_outcome.items(), key=lambda kv: -kv[1])],
            "lr",
        ),
        "Slowest cases (the whole case: read, and write + read back when it parses):",
        "",
        md_table(
            ["case", "file", "mutation", "outcome", "seconds"],
            [[r["case"], r["file"], r["mutation"][:90], r["outcome"], r["seconds"]] for r in slow],
            "rlllr",
        ),
    ]
    lines += [
        "Findings of earlier runs, fixed since (the same run with `--cases 100000 --seed 1` also reported "
        "28 written files whose faces changed on re-reading; all had their positions exactly as promised, "
        "which is what the check now tests, see above):",
        "",
        md_table(
            ["run", "cases", "finding", "fix", "regression test"],
            [list(f) for f in FIXED],
            "lllll",
        ),
    ]
    if findings:
        lines += ["Findings of this run:", ""]
        for r in findings[:40]:
            lines.append(
                f"- case {r['case']} ({r['file']}, {r['mutation'][:100]}): {r['outcome']}"
                + (f" — {r.get('message', '')[:200]}" if r.get("message") else "")
            )
    return "\n".join(lines) + "\n"


def _main(argv: list[str]) -> None:
    if argv[:1] == ["--worker"]:
        worker(int(argv[1]), int(argv[2]))
        return
    if argv[:1] == ["--case"]:
        import argparse

        p = argparse.ArgumentParser(prog="python -m bench.fuzz_formats")
        p.add_argument("--case", type=int, required=True)
        p.add_argument("--seed", type=int, default=2006)
        p.add_argument("--save", help="write the mutated file here")
        a = p.parse_args(argv)
        name, data, desc = make_case(a.seed, a.case, mesh_files(), {})
        print(f"case {a.case} (seed {a.seed}): {name}, {len(data)} bytes: {desc}")
        if a.save:
            Path(a.save).write_bytes(data)
        print(json.dumps(run_case(name, data), indent=1))
        return
    raise SystemExit("use: python -m bench fuzz-formats (or --case N [--seed S] [--save FILE])")


if __name__ == "__main__":
    _main(sys.argv[1:])
