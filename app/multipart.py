"""``multipart/form-data`` bodies, parsed with python-multipart's streaming parser directly.

Starlette's own form parser is not used: its behaviour for our needs (refusing a field given twice,
a text field that is not UTF-8, a body that stops inside a part) could only be had by subclassing
it and reaching into its private attributes, which any Starlette release may rename.  The callbacks
of ``python_multipart.MultipartParser`` are that library's public interface.

What is refused (a :class:`FormError`, turned into a ``bad-form`` problem by the caller), before
anything is kept beyond the limit: more than ``max_files`` files or ``max_fields`` text fields, a
text field over ``max_part_size`` bytes or not UTF-8, a field the route reads given twice, a body
that ends inside a part, and what python-multipart itself refuses (part headers over 4 KiB or more
than 8 of them, broken framing).
"""

from __future__ import annotations

import codecs
from collections.abc import AsyncIterator
from tempfile import SpooledTemporaryFile
from typing import Any

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.datastructures import FormData, Headers, UploadFile


class FormError(Exception):
    """The body is not a form this service takes; the message is for the caller."""


def _decode_name(raw: bytes, charset: str) -> str:
    """A field or file name: names are not checked (unknown fields are ignored), so bytes that
    are not in the form's charset become Latin-1 rather than an error."""
    try:
        return raw.decode(charset)
    except UnicodeDecodeError:
        return raw.decode("latin-1")


class _Part:
    __slots__ = ("data", "file", "headers", "name")

    def __init__(self) -> None:
        self.name = ""
        self.headers: list[tuple[bytes, bytes]] = []
        self.data = bytearray()
        self.file: UploadFile | None = None


class FormParser:
    """One body: feed it with :meth:`parse`.

    Parameters
    ----------
    fields : frozenset of str
        The fields the route reads; only these are refused when given twice (others are ignored).
    max_files, max_fields, max_part_size : int
        Files and text fields in the form; bytes of one text field.
    spool_max_size : int
        A file stays in memory up to this size, then moves to a temporary file.
    """

    def __init__(self, *, fields: frozenset[str], max_files: int, max_fields: int, max_part_size: int,
                 spool_max_size: int) -> None:
        self.fields, self.max_files, self.max_fields = fields, max_files, max_fields
        self.max_part_size, self.spool_max_size = max_part_size, spool_max_size
        self.items: list[tuple[str, str | UploadFile]] = []
        self._files: list[UploadFile] = []
        self._seen: set[str] = set()
        self._charset = "utf-8"
        self._part = _Part()
        self._header_field = bytearray()
        self._header_value = bytearray()
        self._open = False
        self._pending: list[tuple[UploadFile, bytes]] = []
        self._fields = 0

    # -- python-multipart callbacks ------------------------------------------------------------

    def _on_part_begin(self) -> None:
        self._part, self._open = _Part(), True

    def _on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_field += data[start:end]

    def _on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def _on_header_end(self) -> None:
        self._part.headers.append((bytes(self._header_field).lower(), bytes(self._header_value)))
        self._header_field.clear()
        self._header_value.clear()

    def _on_headers_finished(self) -> None:
        part = self._part
        disposition = next((v for k, v in part.headers if k == b"content-disposition"), b"")
        _, options = parse_options_header(disposition)
        if b"name" not in options:
            raise FormError("a part has no name (Content-Disposition: form-data; name=\"...\")")
        part.name = _decode_name(options[b"name"], self._charset)
        if part.name in self._seen and part.name in self.fields:
            raise FormError(f"{field_label(part.name)} is given more than once")
        self._seen.add(part.name)
        if b"filename" in options:
            if len(self._files) >= self.max_files:
                raise FormError(f"Too many files: at most {self.max_files}")
            # closed with the form (FormData.close) or by _close when the body is refused
            spool: Any = SpooledTemporaryFile(max_size=self.spool_max_size)  # noqa: SIM115
            part.file = UploadFile(spool, size=0, filename=_decode_name(options[b"filename"], self._charset),
                                   headers=Headers(raw=part.headers))
            self._files.append(part.file)
        else:
            self._fields += 1
            if self._fields > self.max_fields:
                raise FormError(f"Too many fields: at most {self.max_fields}")

    def _on_part_data(self, data: bytes, start: int, end: int) -> None:
        part = self._part
        if part.file is not None:
            self._pending.append((part.file, data[start:end]))
            return
        if len(part.data) + end - start > self.max_part_size:
            raise FormError(f"{field_label(part.name)} exceeded maximum size of "
                            f"{self.max_part_size // 1024} KiB")
        part.data += data[start:end]

    def _on_part_end(self) -> None:
        part, self._open = self._part, False
        if part.file is not None:
            self.items.append((part.name, part.file))
            return
        try:
            self.items.append((part.name, part.data.decode("utf-8")))
        except UnicodeDecodeError:
            raise FormError(f"{field_label(part.name)} is not valid UTF-8") from None

    # -- driving ------------------------------------------------------------------------------

    async def parse(self, content_type: str, stream: AsyncIterator[bytes]) -> FormData:
        """The form of a body of type ``content_type``; raises :class:`FormError`.  Files are
        closed when the body is refused."""
        _, params = parse_options_header(content_type)
        boundary = params.get(b"boundary")
        if not boundary:
            raise FormError("no boundary in the Content-Type (multipart/form-data; boundary=...)")
        charset = params.get(b"charset", b"utf-8")
        try:
            self._charset = codecs.lookup(charset.decode("latin-1")).name
        except LookupError:
            self._charset = "latin-1"
        parser = MultipartParser(boundary, {
            "on_part_begin": self._on_part_begin, "on_part_data": self._on_part_data,
            "on_part_end": self._on_part_end, "on_header_field": self._on_header_field,
            "on_header_value": self._on_header_value, "on_header_end": self._on_header_end,
            "on_headers_finished": self._on_headers_finished,
        })
        try:
            async for chunk in stream:
                parser.write(chunk)
                await self._flush()
            parser.finalize()
            if self._open:
                raise FormError("it ends inside a part (no closing boundary)")
            for file in self._files:
                await file.seek(0)
        except FormParserError as exc:
            self._close()
            raise FormError(f"the body is not valid multipart data ({exc})") from None
        except BaseException:
            self._close()
            raise
        return FormData(self.items)

    async def _flush(self) -> None:
        """Write the file data of the last chunk (``UploadFile.write`` moves to a thread once the
        file is on disk, so a disk write never blocks the event loop)."""
        for file, data in self._pending:
            await file.write(data)
        self._pending.clear()

    def _close(self) -> None:
        for file in self._files:
            file.file.close()


#: the form fields of the routes; other names are not repeated in messages
FIELD_NAMES = ("mesh", "original", "key", "payload", "method", "strength", "callback_url")


def field_label(name: str) -> str:
    return f"form field '{name}'" if name in FIELD_NAMES else "a form field"
