"""Mesh file formats: sniff, read from bytes, write back with only moved coordinates changed.

>>> doc = read_mesh(data, filename="bunny.ply")
>>> new = [p.vertices + 0.0 for p in doc.parts]
>>> out = doc.write(new)              # same format, same encoding, same bytes elsewhere

Every reader module exports its :class:`FormatSpec`; :data:`FORMATS` lists them, and everything
else that names formats (extensions, media types, messages, the service's documentation) is
derived from it.  A new format is a new module plus one entry here.
"""

from __future__ import annotations

from core.errors import UnsupportedFormatError
from core.formats import gltf, obj, off, ply, stl, tds
from core.formats.base import (
    DEFAULT_LIMITS,
    FormatSpec,
    Limits,
    MeshDocument,
    MeshPart,
    check_coordinates,
    fan_triangulate,
    weld,
)

__all__ = [
    "DEFAULT_LIMITS",
    "FORMATS",
    "FormatSpec",
    "Limits",
    "MeshDocument",
    "MeshPart",
    "detect_format",
    "fan_triangulate",
    "read_mesh",
    "spoken_list",
    "weld",
]

#: every format by name, in the order documentation and messages list them
FORMATS: dict[str, FormatSpec] = {
    spec.name: spec for spec in (obj.SPEC, ply.SPEC, stl.SPEC, off.SPEC, *gltf.SPECS, tds.SPEC)
}
_SNIFF_ORDER = sorted(FORMATS.values(), key=lambda spec: spec.sniff_rank)
_BY_EXTENSION = {ext: spec for spec in FORMATS.values() for ext in spec.extensions}


def spoken_list(words: list[str]) -> str:
    """``"a, b or c"``."""
    return f"{', '.join(words[:-1])} or {words[-1]}" if len(words) > 1 else "".join(words)


def detect_format(data: bytes, filename: str | None = None) -> str:
    """Name of the format of ``data`` from its content, cross-checked with ``filename``'s extension.

    Raises :class:`UnsupportedFormatError` when no format matches, or when the content contradicts
    a known mesh extension.
    """
    if not data:
        raise UnsupportedFormatError("the file is empty (0 bytes): nothing to read")
    found = next((spec for spec in _SNIFF_ORDER if spec.sniff(data, spec.name)), None)
    ext = filename.rsplit(".", 1)[-1].lower() if filename and "." in filename else None
    named = _BY_EXTENSION.get(ext or "")
    if found is None:
        what = f"'.{ext}' file" if named is not None else "file"  # no extension of the caller's echoed
        hint = named.why_not(data) if named is not None and named.why_not is not None else ""
        families = list(dict.fromkeys(spec.family for spec in FORMATS.values()))
        raise UnsupportedFormatError(f"unsupported format: this {what} is not {spoken_list(families)}{hint}")
    if named is not None and ext not in found.extensions:
        raise UnsupportedFormatError(f"file name says '.{ext}' but the content is {found.name.upper()}")
    return found.name


def read_mesh(data: bytes, filename: str | None = None, limits: Limits = DEFAULT_LIMITS) -> MeshDocument:
    """Parse a mesh file from bytes (never from a path or URL).

    Parameters
    ----------
    data : bytes
        The whole file.
    filename : str, optional
        Client-supplied name, used only to cross-check the extension.
    limits : Limits
        Checked before any allocation proportional to a declared count.

    Returns
    -------
    MeshDocument
    """
    limits.check("bytes", len(data))
    spec = FORMATS[detect_format(data, filename)]
    doc = spec.read(data, limits, spec.name)
    for i, part in enumerate(doc.parts):
        check_coordinates(part.vertices, f"mesh part {i}" if len(doc.parts) > 1 else None)
    return doc
