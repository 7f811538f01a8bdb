"""glTF position encodings: float32 and the KHR_mesh_quantization integer types.

A position accessor stores each coordinate as one *component*; :class:`Encoding` turns stored
components into the float64 coordinates the engine works on (mesh-local, before any node
transform, as every glTF reader sees them) and back, so that :meth:`Encoding.quantize` gives
exactly what writing then reading again gives.

Normalized integers follow the glTF 2.0 rules: ``c / M`` for unsigned types and
``max(c / M, -1)`` for signed ones, ``M`` the largest value of the type.  Non-normalized integers
are the integer values themselves (KHR_mesh_quantization puts the scale in the node transform,
which the engine does not need: its statistics are invariant to similarity transforms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FLOAT = 5126
#: componentType -> little-endian storage dtype of a position component
POSITION_DTYPES: dict[int, np.dtype] = {
    5120: np.dtype("<i1"),
    5121: np.dtype("<u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    FLOAT: np.dtype("<f4"),
}


@dataclass(frozen=True)
class Encoding:
    """How one position accessor stores its coordinates.

    Attributes
    ----------
    dtype : numpy dtype
        Little-endian component type.
    normalized : bool
        Integer components mapped to [0, 1] or [-1, 1].
    """

    dtype: np.dtype
    normalized: bool = False

    @property
    def is_float(self) -> bool:
        return self.dtype.kind == "f"

    @property
    def element_size(self) -> int:
        """Bytes of one VEC3 element."""
        return 3 * self.dtype.itemsize

    def _scale(self) -> float:
        return float(np.iinfo(self.dtype).max)

    def decode(self, stored: np.ndarray) -> np.ndarray:
        """Coordinates (float64) of stored components (any shape)."""
        if self.is_float or not self.normalized:
            return np.asarray(stored, dtype=np.float64)
        out = np.asarray(stored, dtype=np.float64) / self._scale()
        return np.maximum(out, -1.0) if self.dtype.kind == "i" else out

    def encode(self, coords: np.ndarray) -> np.ndarray:
        """Stored components (``dtype``) nearest to ``coords``, clipped to the type's range.

        Raises
        ------
        ValueError
            Float32 storage of a NaN, infinite or out-of-range coordinate (a caller bug).
        """
        c = np.asarray(coords, dtype=np.float64)
        if self.is_float:
            out = c.astype(self.dtype)
            if not np.all(np.isfinite(out)):
                raise ValueError("new vertex coordinates must be finite and within the float32 range")
            return out
        info = np.iinfo(self.dtype)
        lo = -info.max if self.normalized and info.min < 0 else info.min
        scaled = c * self._scale() if self.normalized else c
        return np.clip(np.rint(scaled), lo, info.max).astype(self.dtype)

    def quantize(self, coords: np.ndarray) -> np.ndarray:
        """What storing ``coords`` and reading them back gives (float64)."""
        return self.decode(self.encode(coords))

    def json_numbers(self, values: np.ndarray) -> str:
        """A JSON array of stored component values (``min``/``max``): exact doubles or integers."""
        if self.is_float:
            return "[" + ",".join(repr(float(x)) for x in np.asarray(values, dtype=np.float32)) + "]"
        return "[" + ",".join(str(int(x)) for x in values) + "]"

    def same_json(self, old: object, new: np.ndarray) -> bool:
        """Whether a JSON ``min``/``max`` value already equals the stored components ``new``."""
        if not isinstance(old, list) or len(old) != 3:
            return False
        if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in old):
            return False
        try:
            stored = np.asarray(old, dtype=np.float64)
        except OverflowError:
            return False
        if not self.is_float:
            return bool(np.array_equal(stored, np.asarray(new, dtype=np.float64)))
        with np.errstate(over="ignore"):
            return bool(np.array_equal(stored.astype(np.float32), new))
