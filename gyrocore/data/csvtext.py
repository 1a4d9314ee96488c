"""CSV text of the data file: sniffing, the ``#`` header, and the two parsers.

The data rows are parsed by Arrow's streaming C++ reader while the table is clean; from the
first block it refuses (text in a number, a wrong value count, an empty field, a ``#`` line,
bad UTF-8) the exact line parser takes over at that data row, so the messages name the file
line and column (:func:`_csv_blocks`). :mod:`gyrocore.data.recording` builds the
:class:`~gyrocore.data.recording.Recording` from the blocks.
"""

from __future__ import annotations

import itertools
import os
from typing import Iterable, Iterator

import numpy as np

from gyrocore.errors import GyroInputError, warn_repair

__all__ = ["locate_bad_value", "TIME_ALTS", "TIME_NAME_ALTS"]

#: Time columns accepted in place of ``t_s`` (converted to seconds on read): a logger's
#: millisecond, microsecond or nanosecond counter (Arduino millis(), PX4 timestamp, ROS stamps).
TIME_ALTS = {"t_s": 1.0, "t_ms": 1e-3, "t_us": 1e-6, "t_ns": 1e-9}
#: ... and, when none of those is in the header, the long names other tools write with the unit
#: in the name (pyulog's ulog2csv-style ``timestamp_us``, ``time_ms``): read the same way.
TIME_NAME_ALTS = {
    f"{stem}_{u}": f
    for stem in ("time", "timestamp")
    for u, f in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9))
}


def _check_path(path: str) -> None:
    """Existence, folder, permission and empty-file checks with one-line errors."""
    if not os.path.exists(path):
        raise GyroInputError(f"{path}: no such file")
    if os.path.isdir(path):
        raise GyroInputError(f"{path}: is a directory, not a data file")
    if not os.access(path, os.R_OK):
        raise GyroInputError(f"{path}: not readable (permission denied)")
    if os.path.getsize(path) == 0:
        raise GyroInputError(f"{path}: empty file")


#: Compressed files (first bytes, name, the command that unpacks it): a log shared as
#: ``log.csv.gz`` or ``flight.zip`` is named as such, not as "binary file".
_COMPRESSED = (
    (b"\x1f\x8b", "gzip", "gunzip -k FILE"),
    (b"PK\x03\x04", "zip", "unzip FILE"),
    (b"BZh", "bzip2", "bunzip2 -k FILE"),
    (b"\xfd7zXZ\x00", "xz", "unxz -k FILE"),
    (b"\x28\xb5\x2f\xfd", "zstd", "unzstd FILE"),
    (b"7z\xbc\xaf\x27\x1c", "7-Zip", "7z x FILE"),
)


def _sniff_file(path: str) -> None:
    """Existence, folder, empty, binary and encoding checks with one-line errors."""
    _check_path(path)
    with open(path, "rb") as fh:
        head = fh.read(8192)
    if head.startswith(b"\x89HDF") or head.startswith(b"ULog") or head.startswith(b"MATLAB"):
        raise GyroInputError(
            f"{path}: binary file (HDF5/MATLAB/ULog); convert it first: gyroharness convert {path} -o OUT.csv"
        )
    if head.startswith(b"H Product:Blackbox") or head.startswith(b"\xa3\x95\x80"):
        kind = "blackbox log" if head.startswith(b"H") else "ArduPilot DataFlash log"
        raise GyroInputError(
            f"{path}: {kind}, not a data file; convert it first: gyroharness convert {path} -o OUT.csv"
        )
    for magic, kind, how in _COMPRESSED:
        if head.startswith(magic):
            raise GyroInputError(
                f"{path}: {kind}-compressed file; decompress it first ({how.replace('FILE', path)}) and pass the "
                f"file inside"
            )
    if head.startswith((b"\xff\xfe", b"\xfe\xff")) or _utf16_without_bom(head):
        # Excel's "Unicode text", Windows PowerShell's `>` redirect
        raise GyroInputError(
            f"{path}: UTF-16 text (a Windows 'Unicode' export or PowerShell redirect); save it as UTF-8 "
            f"(iconv -f UTF-16 -t UTF-8 {path} > OUT.csv)"
        )
    if b"\x00" in head:
        raise GyroInputError(f"{path}: binary file, expected a CSV data file")
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not just a multibyte char cut at the 8 KiB boundary
            raise GyroInputError(_not_utf8(path, head, exc.start)) from None


def _utf16_without_bom(head: bytes) -> bool:
    """ASCII text stored as UTF-16 without a byte-order mark: every other byte is NUL."""
    h = head[: len(head) // 2 * 2]
    return len(h) >= 8 and (h[1::2].count(0) > 0.9 * len(h) // 2 or h[0::2].count(0) > 0.9 * len(h) // 2)


def _not_utf8(path: str, head: bytes, at: int) -> str:
    """The one-line error for bytes that are not UTF-8: text in a legacy 8-bit encoding (a '°' or
    'µ' from Windows-1252 / Latin-1 in a comment or the header) is named with its line and the
    command that converts it; anything else is called binary."""
    if head.strip(b"\xff") == b"":
        return f"{path}: erased flash (every byte 0xFF): no log or data in it"
    bad = sum(1 for b in head if b < 9 or 13 < b < 32)
    high = sum(1 for b in head if b >= 128)
    if bad == 0 and high <= 0.1 * len(head):  # ASCII text with a few 8-bit characters
        line = head[:at].count(b"\n") + 1
        start = head.rfind(b"\n", 0, at) + 1
        end = head.find(b"\n", at)
        text = head[start : end if end >= 0 else len(head)].decode("cp1252", errors="replace").strip()
        return (
            f"{path}: line {line} is not UTF-8 ({text[:60]!r} in Windows-1252/Latin-1?); save the file as UTF-8 "
            f"(iconv -f WINDOWS-1252 -t UTF-8 {path} > OUT.csv)"
        )
    return f"{path}: not UTF-8 text (binary file?), expected a CSV data file"


def locate_bad_value(path: str, *, skiprows: int, delimiter: str | None = ",", ncols: int | None = None) -> str:
    """One-line description of the first unparseable line of a numeric table.

    Names the file line number (1-based), the column (name when ``header`` known by the
    caller, else 1-based index) and the offending text.
    """
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if lineno <= skiprows:
                continue
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            fields = s.split(delimiter) if delimiter else s.split()
            if ncols is not None and len(fields) != ncols:
                return f"{path}: line {lineno}: {len(fields)} values, expected {ncols}"
            for j, f in enumerate(fields, 1):
                try:
                    float(f)
                except ValueError:
                    return f"{path}: line {lineno}, column {j}: text in a number ({f.strip()[:40]!r})"
    return f"{path}: rows have different numbers of values"


def _parse_rows(
    lines: list[str], first_lineno: int, header: list[str], path: str, *, last: bool = False, first: bool = False
) -> tuple[np.ndarray, int]:
    """Slow exact parser (used when the fast one fails): empty fields → NaN, else one-line errors.

    ``last``: ``lines`` end the file. Its last non-blank line, cut short (fewer values than the
    header names, or a last value that is not a number: a logger stopped mid-write, a copy cut
    off), is dropped with a warning; anywhere else such a line is an error. ``first``: ``lines``
    start the data; a first line of text only is a units row (skipped with a warning, or an error
    when a unit contradicts its column's name). Anywhere, a line repeating the header (files
    joined with ``cat``) is skipped, and one empty field after the last column (``x,y,z,``) is
    ignored; each with a warning.

    Returns the array and the number of empty fields that were read as NaN.
    """
    n = len(header)
    out = []
    n_empty = 0
    k_final = _final_line(lines) if last else -1
    k_first = _first_line(lines) if first else -1
    trailing_comma = False
    for k, line in enumerate(lines):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        f = s.split(",")
        if len(f) == n + 1 and not f[-1].strip():
            # "x,y,z," rows (an Arduino print loop) under a header without the trailing comma
            trailing_comma = True
            f = f[:-1]
        if _is_text_row(f):
            if [_header_name(v) for v in f] == [h if not h.startswith("unnamed_") else "" for h in header]:
                warn_repair(f"{path}: line {first_lineno + k} repeats the header (files joined?): skipped")
                continue
            if k == k_first and len(f) == n:
                _check_units_row(f, header, path, first_lineno + k)
                continue
        if k == k_final and _cut_short(f, n):
            warn_repair(
                f"{path}: last line {first_lineno + k} is cut short ({len(f)} of {n} values, "
                f"{s[-20:]!r}: the write was interrupted?); dropped"
            )
            continue
        if len(f) != n:
            raise GyroInputError(f"{path}: line {first_lineno + k}: {len(f)} values but the header names {n} columns")
        row = []
        for j, v in enumerate(f):
            v = v.strip()
            if v == "":
                n_empty += 1
                row.append(np.nan)
                continue
            try:
                row.append(float(v))
            except ValueError:
                raise GyroInputError(
                    f"{path}: line {first_lineno + k}, column {header[j]!r}: text in a number ({v[:40]!r})"
                ) from None
        out.append(row)
    if trailing_comma:
        warn_repair(f"{path}: data rows end with a comma (an empty field the header does not name): ignored")
    return (np.asarray(out, dtype=float).reshape(-1, n), n_empty)


def _first_line(lines: list[str]) -> int:
    """Index of the first non-blank, non-comment line of ``lines`` (-1 when none)."""
    for k, line in enumerate(lines):
        s = line.strip()
        if s and not s.startswith("#"):
            return k
    return -1


def _is_text_row(fields: list[str]) -> bool:
    """No field of the row is a number, and some are text (a header or a units row, not data)."""
    if not any(v.strip() for v in fields):
        return False
    for v in fields:
        try:
            float(v)
            return False
        except ValueError:
            pass
    return True


def _check_units_row(fields: list[str], header: list[str], path: str, lineno: int) -> None:
    """A row of units under the header (``s,deg/s,deg/s,...``: LabVIEW, motion-capture and
    spreadsheet exports): skipped with a warning when it agrees with the names' units; a unit
    that contradicts the name (deg under ``_rad_s``, rad under ``_deg_s``) is an error (which one
    is right cannot be told from the file)."""
    for h, u in zip(header, fields):
        u_l = u.strip().strip('"').lower()
        clash = ("deg" in u_l and h.endswith("_rad_s")) or ("rad" in u_l and h.endswith("_deg_s"))
        if clash:
            raise GyroInputError(
                f"{path}: line {lineno} gives column {h!r} the unit {u.strip()!r}, which its name contradicts; "
                f"name the column for its unit (gyro_x_rad_s or gyro_x_deg_s) and delete the units row"
            )
    warn_repair(f"{path}: line {lineno} is a row of units ({','.join(v.strip() for v in fields)[:60]!r}): skipped")


def _final_line(lines: list[str]) -> int:
    """Index of the last non-blank, non-comment line of ``lines`` (-1 when none)."""
    for k in range(len(lines) - 1, -1, -1):
        s = lines[k].strip()
        if s and not s.startswith("#"):
            return k
    return -1


def _cut_short(fields: list[str], n: int) -> bool:
    """A row cut off mid-write: fewer than ``n`` values, or all ``n`` with a last one that is
    not a number (``1.2e-``). A row with more values, or with text before its last value, is
    not a truncation."""
    if len(fields) > n:
        return False
    try:
        [float(v) for v in fields[:-1] if v.strip()]
    except ValueError:
        return False
    if len(fields) < n:
        return True
    try:
        float(fields[-1]) if fields[-1].strip() else None
    except ValueError:
        return True
    return False


def _slow_parse(
    lines: list[str], first_lineno: int, header: list[str], path: str, *, last: bool = False, first: bool = False
) -> np.ndarray:
    data, n_empty = _parse_rows(lines, first_lineno, header, path, last=last, first=first)
    if n_empty:
        warn_repair(f"{path}: {n_empty} empty fields read as missing values (NaN)")
    return data


# ---------------------------------------------------------------- the C/Arrow parser
#: Bytes per Arrow CSV block (rounded to whole lines by Arrow). Arrow's streaming reader
#: reads blocks ahead, so its memory grows with the block size: measured on a 608 MiB file,
#: peak RSS above the imports 74 MiB at 256 KiB, 100 MiB at 512 KiB, 225 MiB at 4 MiB, for
#: the same speed (5.3-5.7 s under load 13).
_MIN_BLOCK_BYTES = 256 << 10
_MAX_BLOCK_BYTES = 256 << 10


class _NotClean(Exception):
    """The Arrow parser refused the table (or found empty fields): use the exact parser."""


def _data_offset(path: str, n_skip: int) -> int | None:
    """Byte offset of the first data line, or None when the header lines end in a lone CR
    (old Mac text: the text-mode line count does not match bytes; the exact parser reads it)."""
    with open(path, "rb") as fh:
        for _ in range(n_skip):
            line = fh.readline()
            if b"\r" in line.rstrip(b"\r\n"):
                return None
        return fh.tell()


def _arrow_options(header: list[str], want: list[int], block_size: int | None = None):
    """Arrow CSV options for a clean DESIGN.md table: no quotes, ``,`` only, float64 columns,
    only empty fields as null (``nan``/``inf`` are numbers, as for ``float``)."""
    import pyarrow as pa
    import pyarrow.csv as pc

    names = [f"c{i}" for i in range(len(header))]  # header names were validated already
    ro = pc.ReadOptions(column_names=names, use_threads=True, **({"block_size": block_size} if block_size else {}))
    po = pc.ParseOptions(
        delimiter=",",
        quote_char=False,
        double_quote=False,
        escape_char=False,
        newlines_in_values=False,
        ignore_empty_lines=True,
    )
    co = pc.ConvertOptions(
        column_types={names[i]: pa.float64() for i in want},
        include_columns=[names[i] for i in want],
        null_values=[""],
        strings_can_be_null=False,
        quoted_strings_can_be_null=False,
    )
    return ro, po, co, [names[i] for i in want]


def _is_float64_array(col) -> bool:
    import pyarrow as pa

    return isinstance(col, pa.Array) and pa.types.is_float64(col.type)


def _to_numpy(col) -> np.ndarray:
    """Arrow (chunked) float64 column -> writable numpy array; empty fields -> _NotClean."""
    if col.null_count:
        raise _NotClean("empty fields")
    import pyarrow as pa

    if isinstance(col, pa.Array) and pa.types.is_float64(col.type):
        # the values buffer read directly and copied: the same bytes as to_numpy(), without
        # the ~50 MiB that pyarrow's numpy conversion keeps resident once used (measured on a
        # one-hour 15-column file)
        return np.frombuffer(col.buffers()[1], dtype=np.float64, count=len(col), offset=col.offset * 8).copy()
    arr = col.to_numpy()
    return arr if arr.flags.writeable else arr.copy()


class _Moments:
    """Running per-column mean/variance of columns read only for a check (never held whole);
    shifted sums (shift = first value) keep the variance exact to rounding."""

    def __init__(self, idx: list[int]) -> None:
        self.idx = list(idx)
        self.n = 0
        self.shift = None
        self.s1 = np.zeros(len(idx))
        self.s2 = np.zeros(len(idx))

    def update(self, cols: dict[int, np.ndarray]) -> None:
        if not self.idx:
            return
        x = [cols.pop(i) for i in self.idx]
        if x[0].size == 0:
            return
        if self.shift is None:
            self.shift = np.array([float(v[0]) for v in x])
        for j, v in enumerate(x):
            d = v - self.shift[j]
            self.s1[j] += float(d.sum())
            self.s2[j] += float(np.dot(d, d))
        self.n += x[0].size

    def std(self) -> np.ndarray | None:
        if not self.idx or self.n < 2:
            return None
        m = self.s1 / self.n
        return np.sqrt(np.maximum(self.s2 / self.n - m * m, 0.0))


class _Filler:
    """The final arrays of a whole read (the Recording's own, SI, groups as (N, k)),
    preallocated for an upper bound of the row count and filled block by block: the columns
    are held once — never lists of blocks plus their concatenation (which, with the
    allocator's fragmentation, measured 2-4x the data). Check-only accel columns are reduced
    to running moments."""

    def __init__(self, layout, capacity: int) -> None:
        self.layout = layout
        self.n = 0
        cap = max(int(capacity), 1)
        self.t = np.empty(cap)
        self.groups = {
            name: np.empty((cap, len(blk[0])))
            for name, blk in (
                ("gyro", layout.gyro),
                ("accel", layout.accel),
                ("rref", layout.rref),
                ("qref", layout.qref),
            )
            if blk is not None
        }
        self.temp = np.empty(cap) if layout.temp is not None else None
        self.extra = {h: np.empty(cap) for h, _ in layout.extra}
        self.moments = layout.moments()

    def _arrays(self):
        yield "t", self.t
        yield from self.groups.items()
        if self.temp is not None:
            yield "temp", self.temp
        for h, v in self.extra.items():
            yield "extra:" + h, v

    def _grow(self, need: int) -> None:
        cap = max(need, int(self.t.shape[0] * 1.5) + 1)
        for name, old in list(self._arrays()):
            new = np.empty((cap,) + old.shape[1:])
            new[: self.n] = old[: self.n]
            if name == "t":
                self.t = new
            elif name == "temp":
                self.temp = new
            elif name.startswith("extra:"):
                self.extra[name[6:]] = new
            else:
                self.groups[name] = new

    def add(self, blk: dict[int, np.ndarray]) -> None:
        L = self.layout
        self.moments.update(blk)
        m = len(blk[L.t])
        if m == 0:
            return
        if self.n + m > self.t.shape[0]:
            self._grow(self.n + m)
        s = slice(self.n, self.n + m)
        if L.t_factor == 1.0:
            self.t[s] = blk[L.t]
        else:
            np.multiply(blk[L.t], L.t_factor, out=self.t[s])
        for name, arr in self.groups.items():
            idx, fac = getattr(L, {"gyro": "gyro", "accel": "accel", "rref": "rref", "qref": "qref"}[name])
            for j, (i, f) in enumerate(zip(idx, fac)):
                if f == 1.0:
                    arr[s, j] = blk[i]
                else:
                    np.multiply(blk[i], f, out=arr[s, j])
        if self.temp is not None:
            self.temp[s] = blk[L.temp]
        for h, i in L.extra:
            self.extra[h][s] = blk[i]
        self.n += m

    def columns(self):
        """(t, gyro, accel, temp, rref, qref, extra) trimmed to the rows read (views)."""
        n = self.n
        g = self.groups
        return (
            self.t[:n],
            g["gyro"][:n],
            g["accel"][:n] if "accel" in g else None,
            None if self.temp is None else self.temp[:n],
            g["rref"][:n] if "rref" in g else None,
            g["qref"][:n] if "qref" in g else None,
            {h: v[:n] for h, v in self.extra.items()},
        )


def _count_lines(path: str, offset: int) -> int:
    """Newlines after ``offset`` + 1: an upper bound of the data rows (16 MiB at a time)."""
    n = 1
    with open(path, "rb") as fh:
        fh.seek(offset)
        for chunk in iter(lambda: fh.read(16 << 20), b""):
            n += chunk.count(b"\n")
    return n


def _rechunk(blocks: Iterable[dict[int, np.ndarray]], rows: int) -> Iterator[dict[int, np.ndarray]]:
    """Blocks of any size -> blocks of exactly ``rows`` rows (the last one shorter)."""
    pending: list[dict[int, np.ndarray]] = []
    n_pending = 0
    for blk in blocks:
        m = len(next(iter(blk.values()))) if blk else 0
        if m == 0:
            continue
        pending.append(blk)
        n_pending += m
        if n_pending < rows:
            continue
        cat = {i: np.concatenate([b[i] for b in pending]) for i in pending[0]}
        k = 0
        while n_pending - k >= rows:
            yield {i: v[k : k + rows].copy() for i, v in cat.items()}
            k += rows
        pending = [{i: v[k:] for i, v in cat.items()}] if n_pending > k else []
        n_pending -= k
    if n_pending:
        yield {i: np.concatenate([b[i] for b in pending]) for i in pending[0]}


def _arrow_stream(path: str, offset: int, header: list[str], want: list[int], block_size: int):
    import pyarrow as pa
    import pyarrow.csv as pc

    ro, po, co, names = _arrow_options(header, want, block_size)
    try:
        src = pa.OSFile(path)
        src.seek(offset)
        reader = pc.open_csv(src, read_options=ro, parse_options=po, convert_options=co)
        for batch in reader:
            yield {i: _to_numpy(batch.column(k)) for k, i in enumerate(want)}
    except (pa.ArrowException, UnicodeDecodeError) as exc:
        raise _NotClean(str(exc)) from None


def _block_size(path: str, offset: int, rows: int, ncols: int) -> int:
    with open(path, "rb") as fh:
        fh.seek(offset)
        sample = fh.read(1 << 16)
    per_line = len(sample) / max(sample.count(b"\n"), 1) if sample else 20.0 * ncols
    return int(min(max(rows * per_line, _MIN_BLOCK_BYTES), _MAX_BLOCK_BYTES))


def _data_lines(fh, skip_rows: int, first_lineno: int) -> int:
    """Advance ``fh`` past ``skip_rows`` data rows (blank and ``#`` lines not counted);
    returns the file line number of the next line."""
    lineno = first_lineno
    while skip_rows > 0:
        line = fh.readline()
        if not line:
            break
        lineno += 1
        s = line.strip()
        if s and not s.startswith("#"):
            skip_rows -= 1
    return lineno


def _csv_blocks(
    path: str, header: list[str], n_skip: int, want: list[int], rows: int
) -> Iterator[dict[int, np.ndarray]]:
    """Data blocks of exactly ``rows`` rows: Arrow's streaming C++ reader while the table is
    clean; from the first block it refuses (text in a number, wrong value count, empty
    field, ``#`` line, bad UTF-8) the exact line parser takes over at that data row, so the
    messages name the file line and column and empty fields are counted as before."""
    offset = _data_offset(path, n_skip)
    n_done = 0
    if offset is not None:
        try:
            for blk in _rechunk(
                _arrow_stream(path, offset, header, want, _block_size(path, offset, rows, len(header))), rows
            ):
                yield blk
                n_done += len(blk[want[0]])
            return
        except _NotClean:
            pass
    yield from _exact_blocks(path, header, n_skip, want, n_done, n_skip + 1, rows)


def _header_info(path: str) -> tuple[dict[str, str], list[str], int]:
    try:
        with open(path, "r", encoding="utf-8") as fh:
            meta, header, n_skip = _parse_header(fh, path)
    except UnicodeDecodeError:
        raise GyroInputError(f"{path}: not UTF-8 text, expected a CSV data file") from None
    _check_header(header, path)
    return meta, header, n_skip


def _time_col(header: list[str], path: str) -> tuple[int, float]:
    """Index of the time column (``t_s`` or one of :data:`TIME_ALTS`) and its factor to seconds."""
    found = [(h, header.index(h)) for h in TIME_ALTS if h in header]
    if not found:  # a long name with its unit (timestamp_us) only when no t_* column is there
        found = [(h, header.index(h)) for h in TIME_NAME_ALTS if h in header]
    if len(found) > 1:
        raise GyroInputError(f"{path}: several time columns ({', '.join(h for h, _ in found)}); keep one")
    if not found:
        hint = ""
        if len(header) == 1 and any(c in header[0] for c in ";\t|"):
            sep = next(c for c in ";\t|" if c in header[0])
            hint = (
                f" (the header is one column {header[0][:60]!r}: the file is separated by "
                f"{'tab' if sep == chr(9) else repr(sep)}; a data file is comma-separated)"
            )
        elif len(header) == 1 and len(header[0].split()) > 1 and any(h in TIME_ALTS for h in header[0].split()):
            hint = (
                f" (the header is one column {header[0][:60]!r}: the file is separated by spaces; a data file is "
                f"comma-separated)"
            )
        else:
            hint = _header_hint(header)
        raise GyroInputError(f"{path}: missing required column t_s (or t_ms, t_us, t_ns){hint}")
    h, i = found[0]
    return i, {**TIME_ALTS, **TIME_NAME_ALTS}[h]


def _header_hint(header: list[str]) -> str:
    """What the header row holds, for the "missing column" error: a first row of numbers (no
    header), or the names found (another tool's CSV: ``Time (s)``, ``gx``, ...)."""

    def number(h: str) -> bool:
        try:
            float(h)
        except ValueError:
            return False
        return True

    if header and all(number(h) for h in header if h):
        return (
            f" (the first line, {','.join(header)[:40]!r}, is numbers: the file has no header row; a data file "
            f"starts with one naming its columns t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s,... (docs/data.md))"
        )
    names = ", ".join(repr(h[:30]) for h in header[:6]) + (f", ... ({len(header)} columns)" if len(header) > 6 else "")
    return (
        f" (the header names {names}; a data file names its columns t_s, gyro_x_rad_s or gyro_x_deg_s, ... "
        f"(docs/data.md): rename them, or `gyroharness convert` a source it knows)"
    )


def _check_header(header: list[str], path: str) -> None:
    _time_col(header, path)
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise GyroInputError(f"{path}: duplicate column names in header ({', '.join(dup)})")
    if "" in header:
        raise GyroInputError(f"{path}: empty column name in header")


def _exact_blocks(path, header, n_skip, want, skip_data_rows, first_lineno, rows=200_000):
    """The exact line parser from data row ``skip_data_rows`` on, ``rows`` lines at a time."""
    lineno = first_lineno
    try:
        with open(path, "r", encoding="utf-8", errors="strict") as fh:
            for _ in range(n_skip):
                fh.readline()
            lineno = _data_lines(fh, skip_data_rows, first_lineno)
            lines = list(itertools.islice(fh, rows))
            while lines:
                # one chunk read ahead: the parser must know which lines end the file (a last
                # line cut short is dropped there, an error anywhere else)
                following = list(itertools.islice(fh, rows))
                while following and _final_line(following) < 0:  # blank lines: is there data after them?
                    more = list(itertools.islice(fh, rows))
                    if not more:
                        break
                    following += more
                data = _slow_parse(
                    lines, lineno, header, path, last=_final_line(following) < 0, first=skip_data_rows == 0
                )
                skip_data_rows = -1  # the next chunks do not start the data
                lineno += len(lines)
                if data.shape[0]:
                    yield {i: data[:, i].copy() for i in want}
                lines = following
    except UnicodeDecodeError as exc:  # found by bench/fuzz_reader.py (atheris)
        raise GyroInputError(f"{path}: not UTF-8 text after the header near line {lineno} ({exc.reason})") from None


def _header_name(h: str) -> str:
    """A header field without surrounding whitespace and double quotes (R's write.csv, MATLAB and
    spreadsheets quote the header)."""
    h = h.strip()
    if len(h) >= 2 and h[0] == h[-1] == '"':
        h = h[1:-1].replace('""', '"').strip()
    return h


def _parse_header(lines: Iterable[str], path: str) -> tuple[dict[str, str], list[str], int]:
    """``# key: value`` metadata lines, then the header row; returns (meta, header, lines used)."""
    meta: dict[str, str] = {}
    n_skip = 0
    for line in lines:
        n_skip += 1
        s = line.strip().lstrip("\ufeff")
        if not s:
            continue
        if s.startswith("#"):
            body = s[1:].strip()
            if ":" in body:
                k, v = body.split(":", 1)
                meta[k.strip()] = v.strip()
            continue
        header = [_header_name(h) for h in s.split(",")]
        empty = [i for i, h in enumerate(header) if not h]
        if empty:
            # a pandas index written without a name (to_csv() default), R's row names, a trailing
            # comma: kept as extra columns with a name, said once
            for i in empty:
                header[i] = f"unnamed_{i}"
            warn_repair(
                f"{path}: {len(empty)} column(s) without a name in the header (a pandas/R index, a trailing "
                f"comma?) kept as extra column(s) {', '.join(header[i] for i in empty)}"
            )
        return meta, header, n_skip
    raise GyroInputError(f"{path}: no header row (file is empty or only has comments)")
