"""Mesh file formats: sniff, read from bytes, write back with only moved coordinates changed.

>>> doc = read_mesh(data, filename="bunny.ply")
>>> new = [p.vertices + 0.0 for p in doc.parts]
>>> out = doc.write(new)              # same format, same encoding, same bytes elsewhere
"""

from __future__ import annotations

import importlib

from core.errors import UnsupportedFormatError
from core.formats.base import DEFAULT_LIMITS, Limits, MeshDocument, MeshPart, fan_triangulate, weld

__all__ = [
    "DEFAULT_LIMITS",
    "FORMATS",
    "Limits",
    "MeshDocument",
    "MeshPart",
    "detect_format",
    "fan_triangulate",
    "read_mesh",
    "weld",
]

#: format name -> (module, extensions accepted for it)
FORMATS: dict[str, tuple[str, tuple[str, ...]]] = {
    "glb": ("core.formats.gltf", ("glb",)),
    "gltf": ("core.formats.gltf", ("gltf",)),
    "ply": ("core.formats.ply", ("ply",)),
    "3ds": ("core.formats.tds", ("3ds",)),
    "stl": ("core.formats.stl", ("stl",)),
    "off": ("core.formats.off", ("off",)),
    "obj": ("core.formats.obj", ("obj",)),
}


def detect_format(data: bytes, filename: str | None = None) -> str:
    """Name of the format of ``data`` from its content, cross-checked with ``filename``'s extension.

    Each format module provides ``sniff(data: bytes, name: str) -> bool`` (``name`` is the format
    key, for modules handling two).  Raises :class:`UnsupportedFormatError` when no format matches,
    or when the content contradicts a known mesh extension.
    """
    found = None
    for name, (module, _) in FORMATS.items():
        if importlib.import_module(module).sniff(data, name):
            found = name
            break
    ext = filename.rsplit(".", 1)[-1].lower() if filename and "." in filename else None
    if found is None:
        what = f"'.{ext}' file" if ext else "file"
        hint = ""
        if ext == "stl" and len(data) >= 84:  # binary STL has no magic: its size is its signature
            n = int.from_bytes(data[80:84], "little")
            hint = (f" (as a binary STL it declares {n:,} facets, {84 + 50 * n:,} bytes, "
                    f"but has {len(data):,})")
        raise UnsupportedFormatError(
            f"unsupported format: this {what} is not OBJ, PLY, STL, OFF, glTF/GLB or 3DS{hint}"
        )
    known = {e for _, exts in FORMATS.values() for e in exts}
    if ext in known and ext not in FORMATS[found][1]:
        raise UnsupportedFormatError(f"file name says '.{ext}' but the content is {found.upper()}")
    return found


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
    fmt = detect_format(data, filename)
    module = importlib.import_module(FORMATS[fmt][0])
    doc: MeshDocument = module.read(data, limits, fmt)
    return doc
