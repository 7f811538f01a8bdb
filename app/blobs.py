"""Where the bytes of jobs live: uploads and results, keyed by job.

The memory backend keeps its results here (in a private directory of the API process).  The
Redis backend keeps job *metadata* in Redis and the mesh bytes here, so that a 60 MB upload
never sits in Redis memory or crosses the broker.  :class:`BlobStore` is the interface;
:class:`LocalBlobStore` is a directory, shared by the API and every worker (the same machine, or a
network volume mounted on all of them).

An object store is the production option for machines that share no file system: the S3 API
(``put_object`` / ``get_object`` / ``delete_object`` with boto3, or MinIO's client) maps one to one
on the three methods below.  It is not bundled, to keep the install small.

The methods are synchronous (file and S3 clients are); async callers run them in a thread.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path
from typing import Protocol

_KEY = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,199}")


class BlobNotFound(KeyError):
    """No blob under that key (never written, deleted or expired)."""


class BlobStore(Protocol):
    def put(self, key: str, data: bytes) -> None:
        """Store ``data`` under ``key``, replacing any previous blob; readers see all or nothing."""

    def get(self, key: str) -> bytes:
        """The blob; raises :class:`BlobNotFound` when there is none."""

    def delete(self, key: str) -> None:
        """Forget the blob (no error when there is none)."""


class LocalBlobStore:
    """Blobs as files in one directory (mode 0700, files 0600: uploads hold watermark keys).

    Writes go to a temporary file in the same directory and are renamed into place, so a reader
    (another process, another machine on the same volume) never sees a half-written blob, and a
    writer killed mid-write leaves only a ``.tmp`` file behind.  No ``fsync``: a blob only has to
    outlive its process, not a power cut (its job would then fail with a clear error).
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        self.root.mkdir(mode=0o700, parents=True, exist_ok=True)
        owner = self.root.stat().st_uid
        if hasattr(os, "getuid") and owner != os.getuid():
            raise PermissionError(f"blob directory {self.root} belongs to another user (uid {owner}); "
                                  "set MESHMARK_BLOB_DIR to a directory of your own")

    def _path(self, key: str) -> Path:
        if not _KEY.fullmatch(key):
            raise ValueError(f"invalid blob key {key!r}")
        return self.root / key

    def put(self, key: str, data: bytes) -> None:
        path = self._path(key)
        fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=self.root)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise

    def get(self, key: str) -> bytes:
        try:
            return self._path(key).read_bytes()
        except FileNotFoundError:
            raise BlobNotFound(key) from None

    def delete(self, key: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self._path(key).unlink()
