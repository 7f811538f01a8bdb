"""Builders of hostile uploads for the hardening tests: small, made in code, one per attack.

Every builder returns file bytes; none of them reads anything from disk.  glTF and text-format
helpers of the core tests are reused where they fit (``tests/core/formats``).
"""

from __future__ import annotations

import base64
import io
import json
import socket
import struct
import threading
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import trimesh

from tests.core.formats.test_gltf import to_glb

CANARY_MARKER = b"CANARY-9b1e-the-server-must-never-read-this"


def icosphere(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)


def gltf_document(vertices: np.ndarray, faces: np.ndarray) -> tuple[dict[str, Any], bytes]:
    """A one-mesh glTF (JSON dict, binary buffer) of float32 positions and uint32 indices."""
    pos = np.asarray(vertices, "<f4").tobytes()
    idx = np.asarray(faces, "<u4").tobytes()
    v = np.asarray(vertices, np.float32)
    meta: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"name": "ball", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
             "min": v.min(axis=0).tolist(), "max": v.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5125, "count": int(np.size(faces)), "type": "SCALAR"},
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
                        {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx)}],
        "buffers": [{"byteLength": len(pos) + len(idx)}],
    }
    return meta, pos + idx


def data_uri(blob: bytes) -> str:
    return "data:application/octet-stream;base64," + base64.b64encode(blob).decode()


def gltf_text(meta: dict[str, Any], blob: bytes | None = None) -> bytes:
    """``.gltf`` JSON; ``blob`` (when given) becomes buffer 0 as a ``data:`` URI."""
    meta = json.loads(json.dumps(meta))
    if blob is not None:
        meta["buffers"][0]["uri"] = data_uri(blob)
    return json.dumps(meta, indent=1).encode()


def glb(meta: dict[str, Any], blob: bytes | None) -> bytes:
    return to_glb(meta, blob)


def with_images(meta: dict[str, Any], uris: list[str]) -> dict[str, Any]:
    """The document with one texture image per URI (never to be opened by the server)."""
    meta = json.loads(json.dumps(meta))
    meta["images"] = [{"uri": uri} for uri in uris]
    meta["textures"] = [{"source": i} for i in range(len(uris))]
    return meta


def deep_json(levels: int = 100_000) -> bytes:
    return ('{"asset":{"version":"2.0"},"extras":' + "[" * levels + "]" * levels + "}").encode()


def glb_json_chunk(text: bytes) -> bytes:
    """A GLB holding only a JSON chunk with ``text``."""
    body = text + b" " * (-len(text) % 4)
    return b"glTF" + struct.pack("<IIII", 2, 20 + len(body), len(body), 0x4E4F534A) + body


# --------------------------------------------------------------------------------- PLY / OBJ / STL

def ply_header(fmt: str, vertices: int, faces: int, count: str = "uchar", index: str = "int") -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {faces}\nproperty list {count} {index} vertex_indices\n"
            "end_header\n").encode()


def ply_binary(vertices: np.ndarray, faces: list[list[int]], index: str = "i") -> bytes:
    """Little-endian binary PLY with uchar-counted int (``i``) or uint (``I``) index lists."""
    out = [ply_header("binary_little_endian", len(vertices), len(faces),
                      index="int" if index == "i" else "uint")]
    out.append(np.asarray(vertices, "<f4").tobytes())
    for face in faces:
        out.append(struct.pack(f"<B{len(face)}{index}", len(face), *face))
    return b"".join(out)


def ply_ascii(vertices: np.ndarray, faces: list[list[int]]) -> bytes:
    lines = [" ".join(repr(float(c)) for c in v) for v in vertices]
    lines += [" ".join(map(str, [len(f), *f])) for f in faces]
    return ply_header("ascii", len(vertices), len(faces)) + ("\n".join(lines) + "\n").encode()


def obj_text(vertices: np.ndarray, faces: np.ndarray | list[list[int]], head: str = "") -> bytes:
    lines = [head] if head else []
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, np.float64).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in np.asarray(faces).tolist()]
    return ("\n".join(lines) + "\n").encode()


def binary_stl(triangles: np.ndarray, count: int | None = None) -> bytes:
    tris = np.asarray(triangles, "<f4").reshape(-1, 3, 3)
    records = np.zeros(len(tris), dtype=[("n", "<f4", 3), ("c", "<f4", (3, 3)), ("a", "<u2")])
    records["c"] = tris
    n = len(tris) if count is None else count
    return b"binary stl".ljust(80, b" ") + struct.pack("<I", n) + records.tobytes()


# --------------------------------------------------------------------------------- other formats

JPEG = bytes.fromhex("ffd8ffe000104a46494600010100000100010000ffdb004300") + bytes(range(256)) * 4


def zip_of(files: dict[str, bytes]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in files.items():
            z.writestr(name, data)
    return out.getvalue()


def three_mf() -> bytes:
    """A minimal 3MF package (a zip with a one-triangle model)."""
    model = (b'<?xml version="1.0" encoding="UTF-8"?>\n<model unit="millimeter" '
             b'xmlns="http://schemas.microsoft.com/3dmanufacturing/core/2015/02"><resources>'
             b'<object id="1" type="model"><mesh><vertices><vertex x="0" y="0" z="0"/>'
             b'<vertex x="1" y="0" z="0"/><vertex x="0" y="1" z="0"/></vertices><triangles>'
             b'<triangle v1="0" v2="1" v3="2"/></triangles></mesh></object></resources>'
             b'<build><item objectid="1"/></build></model>\n')
    types = (b'<?xml version="1.0" encoding="UTF-8"?>\n<Types xmlns="http://schemas.openxmlformats.org/'
             b'package/2006/content-types"><Default Extension="model" '
             b'ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/></Types>\n')
    return zip_of({"[Content_Types].xml": types, "3D/3dmodel.model": model})


def billion_laughs_dae() -> bytes:
    """COLLADA XML whose entities expand to 10^9 copies of 'lol' (if anyone expanded them)."""
    entities = ['<!ENTITY lol "lol">'] + [
        f'<!ENTITY lol{i} "{("&lol" + (str(i - 1) if i > 1 else "") + ";") * 10}">' for i in range(1, 10)]
    return ('<?xml version="1.0"?>\n<!DOCTYPE COLLADA [\n' + "\n".join(entities) + "\n]>\n"
            '<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">'
            "<asset><title>&lol9;</title></asset></COLLADA>\n").encode()


# --------------------------------------------------------------------------------- canaries

@contextmanager
def listening_canary() -> Iterator[tuple[int, list[bytes]]]:
    """A TCP listener on 127.0.0.1 that records every connection attempt (none may come):
    ``(port, received)`` where ``received`` gets the first bytes of each connection."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    server.settimeout(0.05)
    received: list[bytes] = []
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except (TimeoutError, OSError):
                continue
            with conn:
                conn.settimeout(0.5)
                try:
                    received.append(conn.recv(256) or b"(connected)")
                except OSError:
                    received.append(b"(connected)")

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1], received
    finally:
        stop.set()
        thread.join(timeout=5)
        server.close()
