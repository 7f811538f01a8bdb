"""Exception tree of the MeshMark engine.

Every error the engine raises on bad input derives from :class:`MeshMarkError`, so the
service can map each subclass to one HTTP problem type.
"""

from __future__ import annotations


class MeshMarkError(Exception):
    """Base class of every error raised by ``core`` on bad input."""


class UnsupportedFormatError(MeshMarkError):
    """The bytes are not one of the supported mesh formats (or contradict the file name)."""


class MeshFormatError(MeshMarkError):
    """The file claims a supported format but is malformed.

    Parameters
    ----------
    message : str
        What is wrong.
    location : str, optional
        Where: ``"line 12"``, ``"byte 4096"``, ``"accessors[3]"``...
    """

    def __init__(self, message: str, location: str | None = None) -> None:
        self.location = location
        super().__init__(f"{message} (at {location})" if location else message)


class LimitExceededError(MeshMarkError):
    """The file is larger than a configured limit (bytes, vertices, faces, meshes, JSON size)."""

    def __init__(self, what: str, value: int, limit: int) -> None:
        self.what, self.value, self.limit = what, value, limit
        super().__init__(f"{what} {value:,} exceeds the limit of {limit:,}")


class DegenerateMeshError(MeshMarkError):
    """The mesh parses but cannot carry a watermark (no faces, all faces degenerate...)."""


class CapacityError(MeshMarkError):
    """Too few carriers for the requested payload at the requested strength."""

    def __init__(self, message: str, carriers: int = 0, needed: int = 0) -> None:
        self.carriers, self.needed = carriers, needed
        super().__init__(message)


class PayloadError(MeshMarkError):
    """Malformed payload bitstring or key."""
