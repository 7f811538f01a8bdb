"""Builders of hostile uploads for the hardening tests: small, made in code, one per attack.

Every builder returns file bytes; none of them reads anything from disk.  Well-formed files of
every format come from the format tests' writers (``tests/core/formats/helpers.py``).
"""

from __future__ import annotations

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

CANARY_MARKER = b"CANARY-9b1e-the-server-must-never-read-this"


def icosphere(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.uint32)


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
