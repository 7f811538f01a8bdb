"""Shared machinery of the text formats (OBJ, ASCII PLY, OFF, ASCII STL).

Everything works on the raw bytes with numpy: lines are found with one ``== b"\\n"`` scan, the
numbers of a group of lines are gathered into one buffer and converted by a single
:func:`numpy.fromstring` call, and the number of tokens of every line is counted from a
whitespace mask.  No Python loop runs per vertex or per face while reading; writing loops only
over the *moved* vertex lines (formatting numbers is per value anyway).

Printing and re-reading are kept consistent: a coordinate printed by :func:`format_coord` with
``d`` decimals reads back as exactly :func:`round_like_text` ``(x, d)`` (both the reader's
:func:`numpy.fromstring` and Python's ``float`` are correctly rounded).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from core.errors import MeshFormatError
from core.formats.base import MeshDocument, fan_triangulate

#: byte -> is ASCII whitespace (the set of :func:`numpy.fromstring` and of ``rb"\\s"``)
WS = np.zeros(256, dtype=bool)
WS[[9, 10, 11, 12, 13, 32]] = True

#: UTF-8 byte order mark, skipped at the start of text files
BOM = b"\xef\xbb\xbf"

_TOKEN = re.compile(rb"\S+")
_COMMENT = re.compile(rb"#[^\n]*")
_NON_WS = re.compile(rb"\S")


@dataclass
class Lines:
    """Line table of a byte buffer (from some start offset).

    Attributes
    ----------
    starts : (L,) int64
        First byte of every line.
    ends : (L,) int64
        End of every line's content (before ``"\\r\\n"`` or ``"\\n"``).
    nexts : (L,) int64
        Start of the following line (``len(data)`` for the last).
    first : (L,) int64
        First non-whitespace byte of every line (``== ends`` for a blank line).
    """

    starts: np.ndarray
    ends: np.ndarray
    nexts: np.ndarray
    first: np.ndarray

    def __len__(self) -> int:
        return int(self.starts.size)

    def blank(self) -> np.ndarray:
        """Mask of blank (whitespace-only) lines."""
        return np.asarray(self.first >= self.ends)


def split_lines(arr: np.ndarray, begin: int = 0) -> Lines:
    """Line table of ``arr[begin:]`` (``arr`` is the file as a uint8 array).

    A final line terminator does not start an extra empty line; a UTF-8 byte order mark at
    the start of the file is skipped (``first``).
    """
    n = int(arr.size)
    nl = np.flatnonzero(arr[begin:] == 10)
    nl += begin
    starts = np.concatenate((np.array([begin], dtype=np.int64), nl + 1))
    ends = np.concatenate((nl, np.array([n], dtype=np.int64)))
    if starts.size > 1 and starts[-1] >= n:
        starts, ends = starts[:-1], ends[:-1]
    nexts = np.concatenate((starts[1:], np.array([n], dtype=np.int64)))
    if n:
        cr = (ends > starts) & (arr[np.maximum(ends - 1, 0)] == 13)
        ends = ends - cr
    first = starts.copy()
    if begin == 0 and n >= 3 and arr[:3].tobytes() == BOM:
        first[0] = 3
    if n:
        active = np.flatnonzero((first < ends) & WS[arr[np.minimum(first, n - 1)]])
        steps = 0
        while active.size and steps < 64:  # indentation: a few vectorised steps
            first[active] += 1
            f = first[active]
            active = active[(f < ends[active]) & WS[arr[np.minimum(f, n - 1)]]]
            steps += 1
        if active.size:  # pathological indentation: search those few lines directly
            data = arr.tobytes()
            for i in active.tolist():
                m = _NON_WS.search(data, int(first[i]), int(ends[i]))
                first[i] = m.start() if m else ends[i]
    return Lines(starts, ends, nexts, first)


def keyword_mask(arr: np.ndarray, lines: Lines, keyword: bytes, fold_case: bool = False) -> np.ndarray:
    """Mask of the lines whose first token is exactly ``keyword``.

    Parameters
    ----------
    arr : uint8 array
        The file.
    lines : Lines
    keyword : bytes
        ASCII keyword (letters are compared case-insensitively when ``fold_case``).
    """
    n = int(arr.size)
    k = len(keyword)
    if n == 0 or len(lines) == 0:
        return np.zeros(len(lines), dtype=bool)
    first = lines.first
    ok = (lines.ends - first) >= k
    for j, c in enumerate(keyword):
        b = arr[np.minimum(first + j, n - 1)]
        if fold_case and chr(c).isalpha():
            ok &= (b | 0x20) == (c | 0x20)
        else:
            ok &= b == c
    after = first + k
    ok &= (after >= lines.ends) | WS[arr[np.minimum(after, n - 1)]]
    return np.asarray(ok)


def gather(arr: np.ndarray, begins: np.ndarray, stops: np.ndarray) -> bytes:
    """Concatenation of the byte ranges ``[begins[i], stops[i])`` (sorted, non-overlapping).

    Ranges normally end at the next line's start so that each keeps its own line terminator.
    """
    if begins.size == 0:
        return b""
    if begins.size == 1 or np.array_equal(begins[1:], stops[:-1]):
        return arr[int(begins[0]) : int(stops[-1])].tobytes()
    mark = np.zeros(arr.size + 1, dtype=np.int8)
    np.add.at(mark, begins, 1)
    np.add.at(mark, stops, -1)
    np.cumsum(mark, out=mark)  # 1 inside a range, 0 outside
    return arr[mark[:-1].view(np.bool_)].tobytes()


def sub_lines(pattern: re.Pattern[bytes], text: bytes, chunk: int = 1 << 20) -> bytes:
    """``pattern.sub(b"", text)`` for a pattern that never crosses a line break, done in chunks
    of about ``chunk`` bytes so that the regex's per-match pieces stay small."""
    if len(text) <= chunk:
        return pattern.sub(b"", text)
    out = []
    start = 0
    while start < len(text):
        stop = text.find(b"\n", start + chunk)
        stop = len(text) if stop < 0 else stop + 1
        out.append(pattern.sub(b"", text[start:stop]))
        start = stop
    return b"".join(out)


def strip_comments(text: bytes) -> bytes:
    """Remove ``#`` comments (to the end of their line)."""
    return sub_lines(_COMMENT, text) if b"#" in text else text


@dataclass
class Block:
    """Numbers of a group of lines.

    Attributes
    ----------
    values : (T,) array
        Every token of the block, in order, converted to the requested dtype.
    counts : (L,) int64
        Number of tokens on every line of the block.
    offsets : (L,) int64
        Index in ``values`` of every line's first token.
    text : uint8 array
        The block's bytes (for :func:`decimals_of`).
    tok_starts, tok_ends : (T,) int64 or None
        Byte span of every token in ``text`` (when asked for).
    """

    values: np.ndarray
    counts: np.ndarray
    offsets: np.ndarray
    text: np.ndarray
    tok_starts: np.ndarray | None = None
    tok_ends: np.ndarray | None = None


def parse_block(
    text: bytes, nlines: int, dtype: type = np.float64, line_numbers: np.ndarray | None = None,
    spans: bool = False, what: str = "number",
) -> Block:
    """Convert the whitespace-separated numbers of ``nlines`` lines (``\\n``-separated).

    Parameters
    ----------
    text : bytes
        The lines, each ending with ``\\n`` (except perhaps the last).
    nlines : int
        Number of lines in ``text``.
    dtype : numpy scalar type
        ``np.float64`` or ``np.int64``.
    line_numbers : (nlines,) int, optional
        0-based line of the file each line of ``text`` comes from, for error locations.
    spans : bool
        Also return the byte span of every token.
    what : str
        Noun for the error message.

    Raises
    ------
    MeshFormatError
        When a token is not a number.
    """
    t = np.frombuffer(text, dtype=np.uint8)
    ws = WS[t]
    tok_ends = None
    if spans:
        end_mask = ~ws
        end_mask[:-1] &= ws[1:]
        tok_ends = np.flatnonzero(end_mask) + 1
        del end_mask
    start_mask = ~ws
    start_mask[1:] &= ws[:-1]
    del ws
    tok_starts = np.flatnonzero(start_mask)
    del start_mask
    nl = np.flatnonzero(t == 10)
    if nl.size > nlines or (nl.size == nlines and nlines and nl[-1] != t.size - 1):
        raise MeshFormatError("unexpected line break")  # caller bug guard, never on valid input
    # tokens before each line break -> tokens per line
    bounds = np.searchsorted(tok_starts, nl[: max(nlines - 1, 0)])
    counts = np.diff(bounds, prepend=0, append=tok_starts.size) if nlines else np.zeros(0, np.int64)
    counts = counts.astype(np.int64)
    del bounds
    total = int(tok_starts.size)
    values: np.ndarray = np.zeros(0, dtype)
    try:
        if total:
            values = np.fromstring(text, dtype=dtype, sep=" ")
        ok = values.size == total
    except ValueError:
        ok = False
    if not ok:
        bad = _first_bad_line(text, nl, tok_starts, dtype)
        where = None
        if 0 <= bad < nlines:
            where = f"line {int(line_numbers[bad]) + 1}" if line_numbers is not None else None
        raise MeshFormatError(f"invalid {what}", where)
    offsets = np.cumsum(counts) - counts
    return Block(values, counts, offsets, t, tok_starts if spans else None, tok_ends)


def _first_bad_line(text: bytes, nl: np.ndarray, tok_starts: np.ndarray, dtype: type) -> int:
    """Index of the first line of ``text`` that does not convert (bisection over prefixes)."""

    def ok(k: int) -> bool:  # do lines [0, k) convert?
        chunk = text[: int(nl[k - 1]) + 1] if k <= nl.size else text
        n_tokens = int(np.searchsorted(tok_starts, len(chunk)))
        try:
            return np.fromstring(chunk, dtype=dtype, sep=" ").size == n_tokens if n_tokens else True
        except ValueError:
            return False

    lo, hi = 0, nl.size + 1  # lines [0, lo) convert; [0, hi) does not
    if ok(hi):
        return -1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return hi - 1


def ragged_take(values: np.ndarray, starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``concatenate([values[s:s+n] for s, n in zip(starts, lengths)])`` without a loop."""
    lengths = np.asarray(lengths, dtype=np.int64)
    if lengths.size and np.all(lengths == lengths[0]):  # uniform (all triangles): no repeat
        k = int(lengths[0])
        return values[(np.asarray(starts, dtype=np.int64)[:, None] + np.arange(k)).reshape(-1)]
    total = int(lengths.sum())
    if total == 0:
        return values[:0]
    shift = np.repeat(np.asarray(starts, dtype=np.int64) - (np.cumsum(lengths) - lengths), lengths)
    return values[shift + np.arange(total)]


def triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """:func:`~core.formats.base.fan_triangulate`, without its temporaries when all are triangles."""
    counts = np.asarray(counts, dtype=np.int64)
    if counts.size and np.all(counts == 3):
        return np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    return fan_triangulate(counts, indices)


def decimals_of(text: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> int | None:
    """Most digits after the point among the tokens ``text[starts[i]:ends[i]]``.

    ``None`` when any of them uses exponent notation.
    """
    if starts.size == 0:
        return 0
    es = np.flatnonzero((text | 0x20) == ord("e"))
    if es.size:
        k = np.searchsorted(es, starts)
        hit = k < es.size
        if np.any(es[np.minimum(k, es.size - 1)][hit] < ends[hit]):
            return None
    dots = np.flatnonzero(text == ord("."))
    if dots.size == 0:
        return 0
    k = np.searchsorted(dots, starts)
    d = dots[np.minimum(k, dots.size - 1)]
    has = (k < dots.size) & (d < ends)
    return int(np.max(np.where(has, ends - d - 1, 0)))


def format_coord(x: float, decimals: int | None) -> str:
    """Text of a rewritten coordinate: ``decimals`` digits after the point, or shortest repr."""
    if decimals is None:
        return repr(float(x))
    return f"{x:.{decimals}f}"


def round_like_text(v: np.ndarray, decimals: int) -> np.ndarray:
    """Exactly what ``float(format_coord(x, decimals))`` gives, for every element of ``v``.

    Where the decimal grid is finer than half the float spacing, that is ``x`` itself.
    Elsewhere :func:`numpy.round` agrees except near ties and when ``|x| * 10**decimals`` is too
    large for its scaled arithmetic to be exact; those few elements go through the formatter.
    """
    if decimals < 0:
        raise ValueError("decimals must be >= 0")
    v = np.asarray(v, dtype=np.float64)
    flat = v.reshape(-1)
    with np.errstate(all="ignore"):
        finite = np.isfinite(flat)
        exact = finite & (10.0**-decimals * 2.001 < np.spacing(np.abs(flat)))
        if decimals <= 22:
            out = np.round(flat, decimals)
            scaled = np.abs(flat) * 10.0**decimals
            frac = scaled - np.floor(scaled)
            # fl(x * 10**d) is within scaled * 2**-53 of the exact product: rint agrees with the
            # exact decimal rounding unless a half-integer is that close
            risky = ~(scaled < 2.0**47) | (np.abs(frac - 0.5) <= scaled * 2.0**-51)
            risky &= finite & ~exact
        else:
            out = flat.copy()
            risky = finite & ~exact
    out[exact] = flat[exact]
    idx = np.flatnonzero(risky)
    if idx.size:
        text = " ".join(f"{x:.{decimals}f}" for x in flat[idx].tolist())
        out[idx] = np.fromstring(text, dtype=np.float64, sep=" ")
    return out.reshape(v.shape)


def moved_slots(slot_to_vertex: np.ndarray, moved: np.ndarray, nvertices: int) -> np.ndarray:
    """Stored slots whose welded vertex is in ``moved``, in file order."""
    mask = np.zeros(nvertices, dtype=bool)
    mask[moved] = True
    return np.flatnonzero(mask[slot_to_vertex])


def patch_lines(
    data: bytes, line_starts: np.ndarray, token_index: np.ndarray, xyz: np.ndarray, decimals: int | None
) -> bytes:
    """Rewrite three tokens on some lines, keeping every other byte.

    Parameters
    ----------
    data : bytes
        The file.
    line_starts : (k,) int
        Start of each line to rewrite (distinct).
    token_index : (k, 3) int
        0-based index, among the line's whitespace-separated tokens, of its x, y and z tokens.
    xyz : (k, 3) float
        New coordinates.
    decimals : int or None
        See :func:`format_coord`.
    """
    order = np.argsort(line_starts, kind="stable")
    pieces: list[bytes] = []
    prev = 0
    for s, toks, coords in zip(
        line_starts[order].tolist(), token_index[order].tolist(), xyz[order].tolist(), strict=True
    ):
        e = data.find(b"\n", s)
        if e < 0:
            e = len(data)
        # tokens end at a "#" comment, even one glued to a number ("1.5#c"), as the readers
        # strip comments before splitting (a PLY vertex line never holds a "#")
        c = data.find(b"#", s, e)
        spans = []
        for m in _TOKEN.finditer(data, s, e if c < 0 else c):
            spans.append(m.span())
            if len(spans) > max(toks):
                break
        if len(spans) <= max(toks):
            raise ValueError(f"line at byte {s} has no token {max(toks)}")  # document bug guard
        repl = sorted(zip(toks, coords, strict=True))
        pieces.append(data[prev:s])
        cur = s
        for ti, c in repl:
            a, b = spans[ti]
            pieces.append(data[cur:a])
            pieces.append(format_coord(c, decimals).encode("ascii"))
            cur = b
        pieces.append(data[cur:e])
        prev = e
    pieces.append(data[prev:])
    return b"".join(pieces)


class TextMeshDocument(MeshDocument):
    """A document written back as text (coordinates printed with :attr:`decimals`).

    :meth:`quantize` is exact: it gives what printing then parsing gives, and keeps rows equal
    to the stored positions unchanged (:meth:`write` does not touch their text).
    """

    def quantize(self, vertices: np.ndarray, decimals: int | None = None) -> np.ndarray:
        """Positions as a :meth:`write` then a new read would give them back.

        Parameters
        ----------
        vertices : (n, 3) float64
        decimals : int, optional
            Override of :attr:`decimals`.
        """
        v = np.asarray(vertices, dtype=np.float64)
        d = self.decimals if decimals is None else decimals
        out = v.copy() if d is None else round_like_text(v, d)
        if len(self.parts) == 1 and v.shape == self.parts[0].vertices.shape:
            same = np.all(v == self.parts[0].vertices, axis=1)
            out[same] = v[same]
        return out

    def _patch_text(
        self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None,
        slot_lines: np.ndarray, slot_tokens: np.ndarray,
    ) -> bytes:
        """Rewrite the x, y, z tokens of the lines of the moved vertices' slots.

        ``slot_lines`` gives each stored slot's line start; ``slot_tokens`` the (3,) or (k, 3)
        token indices of x, y, z on it.
        """
        part = self.parts[0]
        d = self.decimals if decimals is None else decimals
        if d is not None and d < 0:
            raise ValueError("decimals must be >= 0")
        slots = moved_slots(part.slot_to_vertex, moved[0], len(part.vertices))
        if slots.size == 0:
            return self.data
        new = np.asarray(vertices[0], dtype=np.float64)[part.slot_to_vertex[slots]]
        toks = slot_tokens[slots] if slot_tokens.ndim == 2 else np.broadcast_to(slot_tokens, (slots.size, 3))
        return patch_lines(self.data, slot_lines[slots], toks, new, d)


def check_finite(xyz: np.ndarray, line_numbers: np.ndarray | None = None) -> None:
    """Raise :class:`MeshFormatError` on a NaN or infinite coordinate (with its line)."""
    bad = ~np.isfinite(xyz)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        where = f"line {int(line_numbers[row]) + 1}" if line_numbers is not None else None
        raise MeshFormatError("non-finite vertex coordinate (NaN or Inf)", where)


def parse_vertex_lines(arr: np.ndarray, begins: np.ndarray, stops: np.ndarray, count: int,
                       line_numbers: np.ndarray) -> tuple[np.ndarray, int | None]:
    """Positions and printed decimals of vertex lines whose first 3 numbers are x y z (OBJ's
    ``v`` lines after the keyword, OFF's vertex lines).

    Returns
    -------
    positions : (count, 3) float64
    decimals : int or None
        The most decimals printed in those coordinates (None for exponent notation).
    """
    text = strip_comments(gather(arr, begins, stops))
    block = parse_block(text, count, np.float64, line_numbers, spans=True, what="vertex coordinate")
    short = np.flatnonzero(block.counts < 3)
    if short.size:
        line = int(line_numbers[short[0]]) + 1
        raise MeshFormatError("vertex with fewer than 3 coordinates", f"line {line}")
    tok = block.offsets[:, None] + np.arange(3)
    positions = block.values[tok]
    check_finite(positions, line_numbers)
    assert block.tok_starts is not None and block.tok_ends is not None
    return positions, decimals_of(block.text, block.tok_starts[tok], block.tok_ends[tok])
