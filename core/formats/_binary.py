"""Helpers shared by the binary readers that patch float32 coordinates in place (glTF, 3DS)."""

from __future__ import annotations

import numpy as np

from core.errors import MeshFormatError
from core.formats.base import MeshPart

_XYZ_BYTES = np.arange(12, dtype=np.int64)


def moved_slots(part: MeshPart, moved: np.ndarray) -> np.ndarray:
    """Boolean mask of the stored slots of ``part`` whose welded vertex is in ``moved``.

    Parameters
    ----------
    part : MeshPart
    moved : (j,) int
        Indices of moved welded vertices.

    Returns
    -------
    (k,) bool, one per stored slot.
    """
    flag = np.zeros(len(part.vertices), dtype=bool)
    flag[np.asarray(moved, dtype=np.int64)] = True
    mask: np.ndarray = flag[part.slot_to_vertex]
    return mask


def finite_float64(xyz: np.ndarray, where: str | None = None) -> np.ndarray:
    """Stored float32 positions as float64, refusing NaN/Inf before any cast (no FP warnings).

    Raises
    ------
    MeshFormatError
        A stored coordinate is NaN or infinite.
    """
    if not np.all(np.isfinite(xyz)):
        raise MeshFormatError("non-finite vertex coordinate (NaN or Inf)", where)
    return np.asarray(xyz, dtype=np.float64)


def float32_xyz(vertices: np.ndarray) -> np.ndarray:
    """Little-endian float32 copy of ``vertices``, refusing values float32 cannot store.

    Raises
    ------
    ValueError
        A coordinate is NaN, infinite, or overflows float32 (a caller bug, not bad input).
    """
    out = np.asarray(vertices, dtype=np.float64).astype("<f4")
    if not np.all(np.isfinite(out)):
        raise ValueError("new vertex coordinates must be finite and within the float32 range")
    return out.reshape(-1, 3)


def patch_xyz(buf: bytearray, offsets: np.ndarray, values: np.ndarray) -> None:
    """Write ``(x, y, z)`` triples into ``buf`` at byte ``offsets`` (in place), in their own dtype.

    Parameters
    ----------
    buf : bytearray
        Buffer to patch.
    offsets : (j,) int
        Byte offset of each triple (each ``offset + 12 <= len(buf)``).
    values : (j, 3) ndarray, little-endian
        New stored components (float32, or the integer types of quantized glTF).
    """
    if len(offsets) == 0:
        return
    view = np.frombuffer(buf, dtype=np.uint8)
    raw = np.ascontiguousarray(values).view(np.uint8).reshape(len(offsets), -1)
    width = raw.shape[1]
    view[np.asarray(offsets, dtype=np.int64)[:, None] + _XYZ_BYTES[:width]] = raw
