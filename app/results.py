"""Engine results as HTTP answers (body, media type, headers), the same for the synchronous routes
and the job results, whichever process renders them."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from typing import Any

from app.preview import PREVIEW_MEDIA_TYPE, pack
from core.api import EmbeddedFile
from core.formats import FORMATS
from core.preview import PreviewGeometry

#: documented response headers of an embedding (name -> description); the README lists the same
EMBED_HEADERS: dict[str, str] = {
    "X-MeshMark-Method": "Embedding method (`ellipsoids` or `planes`).",
    "X-MeshMark-Payload-Bits": "Payload length in bits (32 for the key-derived code).",
    "X-MeshMark-Carriers": "Carrier vertices under this key, all mesh parts together (one codeword bit "
                           "each; those already inside their margin, and the report's `skipped`, do not "
                           "move). `/v1/capacity` with the same key gives the same count.",
    "X-MeshMark-Copies": "Carriers per codeword bit.",
    "X-MeshMark-Vertices-Moved": "Vertices whose stored position changed (not the carrier count).",
    "X-MeshMark-RMS-Displacement": "RMS vertex displacement / bounding-box diagonal.",
    "X-MeshMark-Max-Displacement": "Largest vertex displacement / bounding-box diagonal.",
    "X-MeshMark-Hausdorff": "Symmetric Hausdorff distance / bounding-box diagonal.",
    "X-MeshMark-Skipped-Elements": "Elements of the file that are not triangles (faces of fewer than 3 "
                                   "distinct corners, OBJ `l`/`p` lines, glTF point and line primitives): "
                                   "not watermarked, written back untouched.",
    "X-MeshMark-Reencoded": "Compressed encodings whose streams were re-encoded with the settings read "
                            "from the file (`draco`, `meshopt`), comma-separated; `none` when every "
                            "other byte was kept.",
    "X-MeshMark-Layers": "The layers that read the payload on their own, comma-separated: "
                         "`connectivity` (always: carriers found by the mesh's connectivity, which "
                         "survive crops and extracted parts) and `geometry` when the carriers found by "
                         "position in the surface's frame do too (they survive re-triangulation).",
    "X-MeshMark-Report": "The whole embedding report as compact JSON.",
}

#: ``Content-Type`` of a watermarked mesh, one per format
MESH_MEDIA_TYPES = tuple(spec.media_type for spec in FORMATS.values())

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass(frozen=True)
class Rendered:
    """An answer ready to send: body, media type, extra headers."""

    body: bytes
    media_type: str
    headers: dict[str, str] = field(default_factory=dict)


def safe_stem(filename: str | None) -> str:
    """A file-name stem that is safe inside a quoted ``Content-Disposition`` value."""
    name = re.split(r"[\\/]", filename or "")[-1]
    stem = name.rsplit(".", 1)[0] if "." in name else name
    stem = _UNSAFE.sub("_", stem).strip("._")[:80]
    return stem or "mesh"


def _json(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


def embedded_result(embedded: EmbeddedFile, filename: str | None) -> Rendered:
    """The marked mesh, named after the upload, with the report in ``X-MeshMark-*`` headers."""
    report = embedded.report
    headers = {
        "Content-Disposition": f'attachment; filename="{safe_stem(filename)}.marked.{embedded.extension}"',
        "X-MeshMark-Method": report.method,
        "X-MeshMark-Payload-Bits": str(report.payload_bits),
        "X-MeshMark-Carriers": str(report.carriers),
        "X-MeshMark-Copies": f"{report.copies:g}",
        "X-MeshMark-Vertices-Moved": str(report.vertices_moved),
        "X-MeshMark-RMS-Displacement": f"{report.rms_displacement:.6g}",
        "X-MeshMark-Max-Displacement": f"{report.max_displacement:.6g}",
        "X-MeshMark-Hausdorff": f"{report.hausdorff:.6g}",
        "X-MeshMark-Skipped-Elements": str(report.skipped_elements),
        "X-MeshMark-Reencoded": ",".join(report.reencoded) or "none",
        "X-MeshMark-Layers": ",".join(report.layers),
        "X-MeshMark-Report": _json(report.to_dict()).decode("ascii"),
    }
    return Rendered(embedded.data, embedded.media_type, headers)


def json_result(value: Any) -> Rendered:
    """A report with ``to_dict()`` as a JSON body."""
    return json_answer(value.to_dict())


def json_answer(value: Any) -> Rendered:
    return Rendered(_json(value), "application/json")


#: documented response headers of a fingerprinted copy, besides those of an embedding
COPY_HEADERS: dict[str, str] = {
    "X-MeshMark-Asset-Id": "The asset the copy is registered under (the caller's `asset_id`, or the "
                           "SHA-256 of the uploaded cover): give it to `/v1/trace`.",
    "X-MeshMark-Codeword-Bits": "Length of the recipient's codeword.",
    "X-MeshMark-Fingerprint-Score": "Score of the recipient's codeword read back from the copy before "
                                    "sending it (an innocent scores above t with probability <= "
                                    "exp(-t^2/2)).",
}


def copy_result(embedded: EmbeddedFile, filename: str | None, asset_id: str, codeword_bits: int,
                score: float) -> Rendered:
    """A fingerprinted copy: the marked mesh of :func:`embedded_result` with :data:`COPY_HEADERS`."""
    out = embedded_result(embedded, filename)
    out.headers.update({"X-MeshMark-Asset-Id": asset_id, "X-MeshMark-Codeword-Bits": str(codeword_bits),
                        "X-MeshMark-Fingerprint-Score": f"{score:.2f}"})
    return out


def preview_result(geometry: PreviewGeometry) -> Rendered:
    """A mesh for the viewer in the binary layout of :mod:`app.preview`, never cached (it
    depends on files the URL does not name)."""
    return Rendered(pack(geometry), PREVIEW_MEDIA_TYPE, {"Cache-Control": "no-store"})
