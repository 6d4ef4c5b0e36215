"""A small strict CSV reader/writer, the recording error, and atomic file writes.

Every file of a recording is read through :func:`read_table` (or the JSON/YAML readers in
:mod:`jaxtraj.io.json_formats`), so bad input stops with one message of the form
``PATH:LINE: problem`` (:class:`RecordingError`), the line 1-based as an editor shows it.

Writers go through :func:`atomic_write_text` / :func:`atomic_folder`: the result appears
under its final name only once it is complete, so an interrupted run never leaves a
half-written file that looks finished.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = [
    "RecordingError",
    "Table",
    "atomic_folder",
    "atomic_write_bytes",
    "atomic_write_text",
    "read_header",
    "read_table",
    "write_table",
]

KINDS = ("float", "int", "int64ns", "str")


def _show(value) -> str:
    """``repr`` of a number for messages (a NumPy scalar shown as the plain Python value)."""
    return repr(value.item() if isinstance(value, np.generic) else value)


class RecordingError(ValueError):
    """Bad input in a recording file; ``str()`` is ``"PATH:LINE: problem"`` or ``"PATH: problem"``.

    Attributes:
        path: the file (a :class:`~pathlib.Path`).
        line: 1-based line number, or None where the problem has no line (a JSON key, a
            missing file).
        problem: what is wrong, in words.
    """

    def __init__(self, path: str | Path, line: int | None, problem: str):
        self.path = Path(path)
        self.line = None if line is None else int(line)
        self.problem = str(problem)
        super().__init__(str(self))

    def __str__(self) -> str:
        where = str(self.path) if self.line is None else f"{self.path}:{self.line}"
        return f"{where}: {self.problem}"

    def __reduce__(self):
        return (type(self), (self.path, self.line, self.problem))


class Table(dict):
    """The columns read by :func:`read_table` (name -> (N,) array), plus where they came from.

    Attributes:
        path: the file read.
        lines: (N,) int64, the 1-based line number of each data row (after sorting).
    """

    def __init__(self, path: Path, lines: np.ndarray, columns: Mapping[str, np.ndarray]):
        super().__init__(columns)
        self.path = path
        self.lines = lines

    def error(self, row: int, problem: str) -> RecordingError:
        """A :class:`RecordingError` at data row ``row`` (0-based) of this table."""
        return RecordingError(self.path, int(self.lines[row]), problem)


def _check_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise RecordingError(path, None, "no such file")
    if not path.is_file():
        raise RecordingError(path, None, "expected a file, found a folder or special file")
    return path


def _read_lines(path: Path) -> list[str]:
    try:
        with path.open(encoding="utf-8-sig", newline=None) as fh:
            return fh.read().split("\n")
    except UnicodeDecodeError as err:
        line = 1  # find the line of the offending byte for the message
        with path.open("rb") as fh:
            line += fh.read(err.start).count(b"\n")
        raise RecordingError(path, line, f"not UTF-8 text ({err.reason})") from None
    except OSError as err:
        raise RecordingError(path, None, f"cannot read ({err.strerror})") from None


def _split(line: str, sep: str | None) -> list[str]:
    return [c.strip() for c in line.split(sep)] if sep else line.split()


def _find_header(
    path: Path, lines: list[str], names: Iterable[str], sep: str | None
) -> tuple[int, list[str]]:
    """Index of the header line and its cells.

    The header is the first line that is neither blank nor a ``#`` comment, unless that line
    names none of ``names`` and an earlier ``#`` line does (EuRoC's ``#timestamp [ns],...``):
    then the last such ``#`` line is the header.
    """
    names = set(names)
    hash_header = None
    for i, raw in enumerate(lines):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            cells = _split(line[1:], sep)
            if names.intersection(cells):
                hash_header = (i, cells)
            continue
        cells = _split(line, sep)
        if hash_header is not None and not names.intersection(cells):
            return hash_header
        return i, cells
    if hash_header is not None:
        return hash_header
    raise RecordingError(
        path, None, f"empty file: expected a header line with the columns {', '.join(names)}"
    )


def read_header(
    path: str | Path, names: Iterable[str], *, sep: str | None = ","
) -> tuple[int, list[str]]:
    """The header line of a table file (to choose between formats before reading it).

    Args:
        path: the file.
        names: column names that may appear in the header (used to tell a ``#`` header
            from a ``#`` comment).
        sep: cell separator; None splits at runs of whitespace.

    Returns:
        ``(line, cells)``: the 1-based line number and the stripped header cells.
    """
    path = _check_file(path)
    i, cells = _find_header(path, _read_lines(path), list(names), sep)
    return i + 1, cells


def _parse(kind: str, cells: list[str]) -> np.ndarray:
    if kind == "float":
        if "" in cells:
            raise ValueError("empty cell")
        return np.array(cells, dtype=np.float64)
    if kind in ("int", "int64ns"):
        return np.array(cells, dtype=np.int64)
    return np.array([c.strip() for c in cells], dtype=str)


def _parse_one(kind: str, cell: str) -> None:
    """Raise ValueError if ``cell`` is not a valid ``kind`` (the slow path's check)."""
    if kind == "float":
        if not cell:
            raise ValueError("empty cell")
        float(cell)
    elif kind in ("int", "int64ns"):
        if not cell:
            raise ValueError("empty cell")
        value = int(cell)
        if not -(2**63) <= value < 2**63:
            raise ValueError("out of the int64 range")


_KIND_WORDS = {
    "float": "a number",
    "int": "an integer",
    "int64ns": "an integer timestamp in nanoseconds",
}


def read_table(
    path: str | Path,
    columns: Mapping[str, str],
    *,
    aliases: Mapping[str, Sequence[str]] | None = None,
    sort_key: str | None = None,
    strictly_increasing: str | None = None,
    allow_nonfinite: Iterable[str] = (),
    sep: str | None = ",",
    header: bool = True,
) -> Table:
    """Read a comma-separated table strictly: every problem stops with ``PATH:LINE: problem``.

    The first line that is not blank and not a ``#`` comment is the header (a ``#`` before
    the header, as in EuRoC files, is allowed); later ``#`` lines and blank lines are
    skipped; cells are stripped of surrounding whitespace. Extra header columns are allowed
    and ignored; every row must have as many cells as the header.

    Args:
        path: the file.
        columns: wanted column name -> kind: ``"float"`` (finite float64), ``"int"``
            (int64), ``"int64ns"`` (int64 timestamp in ns) or ``"str"``. Without a header
            (``header=False``) the columns are taken in this order.
        aliases: column name -> other header spellings accepted for it.
        sort_key: a column to sort the rows by (stable) before the checks.
        strictly_increasing: a time column that must increase strictly from row to row.
        allow_nonfinite: float columns in which NaN and inf are allowed.
        sep: cell separator; None splits at runs of whitespace (TUM files).
        header: False for files whose rows start at the first non-comment line.

    Returns:
        A :class:`Table`: ``{name: (N,) array}`` (float64, int64 or str) with ``.lines``.

    Raises:
        RecordingError: missing file, missing header columns, wrong number of cells, an
            unparsable number, NaN/inf, a time column that does not increase, no rows.
    """
    path = _check_file(path)
    for name, kind in columns.items():
        if kind not in KINDS:
            raise ValueError(f"columns[{name!r}]: expected one of {KINDS}, got {kind!r}")
    aliases = dict(aliases or {})
    lines = _read_lines(path)

    if header:
        names = set(columns) | {a for alts in aliases.values() for a in alts}
        head, cells = _find_header(path, lines, names, sep)
        if len(set(cells)) != len(cells):
            dup = sorted({c for c in cells if cells.count(c) > 1})
            raise RecordingError(path, head + 1, f"repeated header column(s): {', '.join(dup)}")
        index, missing = {}, []
        for name in columns:
            found = [c for c in (name, *aliases.get(name, ())) if c in cells]
            if found:
                index[name] = cells.index(found[0])
            else:
                missing.append(name)
        if missing:
            raise RecordingError(
                path,
                head + 1,
                f"missing header column(s) {', '.join(missing)}; "
                f"found {', '.join(cells) if cells else 'none'}",
            )
        ncells, start = len(cells), head + 1
    else:
        index = {name: j for j, name in enumerate(columns)}
        ncells, start = None, 0

    # Fast path: split all rows at once, then convert whole columns with NumPy; on a
    # conversion error, walk the column cell by cell to find the offending line.
    data, linenos = [], []
    for i in range(start, len(lines)):
        line = lines[i].strip()
        if line and line[0] != "#":
            data.append(line)
            linenos.append(i + 1)
    if not data:
        raise RecordingError(path, None, "no data rows")
    if ncells is None:
        ncells = len(columns)
    if sep:
        lens = np.fromiter((row.count(sep) for row in data), np.int64, len(data)) + 1
        flat = sep.join(data).split(sep)
    else:
        split = [row.split() for row in data]
        lens = np.fromiter((len(row) for row in split), np.int64, len(data))
        flat = [c for row in split for c in row] if np.all(lens == ncells) else []
    bad = np.flatnonzero(lens != ncells)
    if bad.size:
        r = int(bad[0])
        raise RecordingError(
            path, linenos[r], f"expected {ncells} cells (as in the header), got {lens[r]}"
        )
    out = {}
    for name, kind in columns.items():
        cells = flat[index[name] :: ncells]
        try:
            out[name] = _parse(kind, cells)
        except (ValueError, OverflowError):
            for r, cell in enumerate(cells):
                try:
                    _parse_one(kind, cell.strip())
                except (ValueError, OverflowError):
                    raise RecordingError(
                        path,
                        linenos[r],
                        f"column {name}: expected {_KIND_WORDS[kind]}, got {cell.strip()!r}",
                    ) from None
            raise  # pragma: no cover  (NumPy and Python disagree on a cell)
    lines_arr = np.asarray(linenos, np.int64)

    if sort_key is not None:
        order = np.argsort(out[sort_key], kind="stable")
        out = {k: v[order] for k, v in out.items()}
        lines_arr = lines_arr[order]
    table = Table(path, lines_arr, out)

    allow = set(allow_nonfinite)
    first_bad = None
    for name, kind in columns.items():
        if kind != "float" or name in allow:
            continue
        bad = np.flatnonzero(~np.isfinite(out[name]))
        if bad.size and (first_bad is None or lines_arr[bad[0]] < lines_arr[first_bad[0]]):
            first_bad = (int(bad[0]), name)
    if first_bad is not None:
        r, name = first_bad
        raise table.error(r, f"column {name}: expected a finite number, got {_show(out[name][r])}")

    if strictly_increasing is not None:
        t = out[strictly_increasing]
        bad = np.flatnonzero(t[1:] <= t[:-1])
        if bad.size:
            r = int(bad[0]) + 1
            if t[r] == t[r - 1]:
                problem = f"duplicate timestamp {_show(t[r])} (also on line {lines_arr[r - 1]})"
            else:
                problem = f"timestamp goes backwards ({_show(t[r])} after {_show(t[r - 1])})"
            raise table.error(r, f"column {strictly_increasing}: {problem}")
    return table


def _format_column(name: str, col: np.ndarray, fmt: str | None) -> list[str]:
    if fmt is not None:
        return [fmt % v for v in col.tolist()]
    if col.dtype.kind == "f":
        return [repr(v) for v in col.astype(np.float64).tolist()]  # shortest exact repr
    if col.dtype.kind in "iub":
        return [str(int(v)) for v in col.tolist()]
    cells = [str(v) for v in col.tolist()]
    for v in cells:
        if "," in v or "\n" in v or "\r" in v or v != v.strip() or v.startswith("#"):
            raise ValueError(
                f"columns[{name!r}]: cells may not contain commas or line breaks, nor start "
                f"with '#' or whitespace; got {v!r}"
            )
    return cells


def write_table(
    path: str | Path,
    header: Sequence[str],
    columns: Sequence[np.ndarray],
    *,
    fmt: Sequence[str | None] | None = None,
) -> None:
    """Write a comma-separated table atomically (readable back by :func:`read_table`).

    Floats are written with Python's shortest repr, which round-trips float64 exactly
    (``nan``/``inf`` are written as such); integers in full.

    Args:
        path: destination file.
        header: N column names.
        columns: N arrays of equal length (R,).
        fmt: optional per-column ``%``-format strings (None entries: the default).
    """
    if len(header) != len(columns):
        raise ValueError(
            f"header: expected {len(columns)} names (one per column), got {len(header)}"
        )
    for name in header:
        if "," in name or "\n" in name or name != name.strip() or not name:
            raise ValueError(f"header: expected plain column names, got {name!r}")
    fmt = [None] * len(columns) if fmt is None else list(fmt)
    if len(fmt) != len(columns):
        raise ValueError(f"fmt: expected {len(columns)} entries, got {len(fmt)}")
    cols = [np.asarray(c) for c in columns]
    for name, col in zip(header, cols, strict=True):
        if col.ndim != 1 or col.shape[0] != cols[0].shape[0]:
            raise ValueError(
                f"columns[{name!r}]: expected shape ({cols[0].shape[0]},), got {col.shape}"
            )
    cells = [_format_column(n, c, f) for n, c, f in zip(header, cols, fmt, strict=True)]
    body = "\n".join(",".join(row) for row in zip(*cells, strict=True))
    atomic_write_text(path, ",".join(header) + "\n" + body + ("\n" if body else ""))


def _part_path(path: Path) -> Path:
    return path.with_name("." + path.name + ".part")


def _fsync_dir(folder: Path) -> None:
    if os.name != "posix":
        return
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically.

    The bytes go to the hidden ``.NAME.part`` beside ``path``, are flushed and fsynced, and
    the file is renamed over ``path`` (``os.replace``). On any error the ``.part`` file is
    removed and ``path`` is left as it was.
    """
    path = Path(path)
    part = _part_path(path)
    try:
        with part.open("wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(part, path)
    except BaseException:
        with contextlib.suppress(OSError):
            part.unlink()
        raise
    _fsync_dir(path.parent)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically as UTF-8; see :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def atomic_folder(final: str | Path) -> Iterator[Path]:
    """Build a folder under a temporary name and put it in place of ``final`` at the end.

    Yields a fresh empty folder ``.NAME.part-XXXX`` beside ``final``. On normal exit an
    existing ``final`` is moved aside, the new folder renamed to ``final``, and the old one
    deleted. On an exception the temporary folder is removed and ``final`` is untouched.

    Args:
        final: the folder to create or replace.
    """
    final = Path(final)
    if final.name in ("", ".", ".."):
        raise ValueError(f"final: expected a folder path with a name, got {str(final)!r}")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.part-", dir=final.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    try:
        if final.exists() or final.is_symlink():
            old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-", dir=final.parent))
            old.rmdir()
            os.replace(final, old)
        os.replace(tmp, final)
    except BaseException:
        if old is not None and not final.exists():
            os.replace(old, final)
            old = None
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    old.unlink()
    _fsync_dir(final.parent)
