"""The CSV files of a session (``sensors.csv``, ``mocap.csv``): read fast, and when anything is
wrong, read again cell by cell to name the line and the column; written back at full precision.

Plain NumPy and the standard library (pyarrow's CSV reader first when it is installed: it is a
dependency for speed, measured in benchmarks/front_door.py), at the edge of the package.
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from ._atomic import atomic_write

META_FILE = "meta.json"
SENSORS_FILE = "sensors.csv"
MOCAP_FILE = "mocap.csv"


class SessionError(ValueError):
    """A malformed session, in one user-facing line.

    The message names the file, the row (its line number in the file, the header being line 1)
    and/or the column, what was found and what was expected.
    """


def _read_text(file: str) -> str:
    return _decode(file, _read_bytes(file))


def _read_bytes(file: str) -> bytes:
    try:
        with open(file, "rb") as f:
            return f.read()
    except FileNotFoundError:
        raise SessionError(
            f"{file}: file not found (a session folder holds {META_FILE}, {SENSORS_FILE} "
            f"and optionally {MOCAP_FILE})"
        ) from None
    except OSError as e:
        raise SessionError(f"{file}: cannot read ({e.strerror})") from None


def _decode(file: str, raw: bytes) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise SessionError(f"{file}: not UTF-8 text (byte {e.start}: {e.reason})") from None


def _read_csv(
    file: str, required: Sequence[str], optional: Sequence[str], context: str,
    rename: Mapping[str, str] | None = None,
) -> dict[str, np.ndarray]:
    """The ``required`` and present ``optional`` columns of a CSV file as float64 arrays.

    ``rename`` (``meta.json``'s ``mocap_columns``) gives the file's name of a required column
    where it differs from ours (``_columns_for``); the result is keyed by our names.

    Blank lines are skipped; an empty cell or ``nan`` is NaN; ``t`` (the first required
    column) must be present in every row, finite and strictly increasing; no cell may be
    infinite or text. A fast path (pyarrow, else ``np.loadtxt``) reads well-formed files;
    anything it cannot read, or any problem in what it read, is read again cell by cell to
    report the first problem with its line number.
    """
    raw = _read_bytes(file)
    text = _decode(file, raw)
    nl = text.find("\n")
    header_line = text if nl < 0 else text[:nl]
    header = [name.strip() for name in next(csv.reader([header_line.rstrip("\r")]), [])]
    if not any(header):
        raise SessionError(f"{file}, line 1: expected a header row of column names, got none")
    ours = (*required, *(n for n in optional if n in header))
    if rename:
        required = _columns_for(file, required, header, rename, context)
    wanted = (*required, *(n for n in optional if n in header))
    missing = [n for n in required if n not in header]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise SessionError(f"{file}: missing column {missing[0]!r}{more} ({context})")
    for name in wanted:
        if header.count(name) > 1:
            raise SessionError(f"{file}, line 1: column {name!r} appears more than once")
    index = [header.index(n) for n in wanted]

    values = _parse_arrow(raw, len(header), index)
    del raw
    if values is None:
        values = _parse_fast("" if nl < 0 else text[nl + 1:], len(header), index)
    values = _checked(file, values, wanted, "no data rows after the header line",
                      lambda: _parse_slow(file, "" if nl < 0 else text[nl + 1:], header, wanted,
                                          index))
    return {name: np.ascontiguousarray(values[:, j]) for j, name in enumerate(ours)}


def _checked(file: str, values: np.ndarray | None, names: Sequence[str], empty: str,
             slow: Callable[[], tuple[np.ndarray, list[int]]]) -> np.ndarray:
    """``values`` (a fast path's, None if it could not read the file) when they have no
    problem (``_first_problem``); else the file read again cell by cell (``slow``: the values
    and each row's line number; it raises on a malformed row or cell), and a one-line
    ``SessionError`` naming the line of the first problem (``empty``: the message when there
    are no rows)."""
    if values is not None and _first_problem(values, names) is None:
        return values
    values, lines = slow()
    if not lines:
        raise SessionError(f"{file}: {empty}")
    problem = _first_problem(values, names)
    if problem is not None:
        row, message = problem
        raise SessionError(f"{file}, line {lines[row]}{message}")
    return values


def _columns_for(file: str, names: Sequence[str], available: Sequence[str],
                 mapping: Mapping[str, str], context: str) -> list[str]:
    """The file's column (or channel label) for each of our ``names``: ``mapping[name]``
    (``meta.json``'s ``mocap_columns``) where the file has it, else the name itself (so a
    session written back with our names still reads); a one-line ``SessionError`` naming the
    first of ours that matches nothing, what the file has, and ``mocap_columns``."""
    out = []
    for name in names:
        theirs = mapping.get(name)
        if theirs is not None and theirs in available:
            out.append(theirs)
        elif name in available:
            out.append(name)
        else:
            via = (f"nor {theirs!r} (its name in meta.json's mocap_columns)" if theirs is not None
                   else "and meta.json's mocap_columns names no other column for it")
            raise SessionError(
                f"{file}: no column {name!r} {via} ({context}); it has {_listing(available)}"
                f"; map each of our angles to its column in mocap_columns, e.g. "
                f'"mocap_columns": {{"{name}": "<column>"}}')
    return out


def _listing(names: Sequence[str], most: int = 10) -> str:
    """Names for a message: quoted, the first ``most`` and how many more."""
    shown = ", ".join(repr(n) for n in names[:most])
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return f"{shown}{more}" if names else "no columns"


def _parse_arrow(raw: bytes, n_cols: int, index: list[int]) -> np.ndarray | None:
    """The wanted columns of the data rows via pyarrow's CSV reader (several threads, about 8x
    ``np.loadtxt`` on an hour of readings: benchmarks/front_door.py), or None when pyarrow is
    not installed or the file is not plain numbers (the other paths then name the problem).

    Reads exactly what the format allows: an empty cell, ``nan`` or ``NaN`` is NaN, anything
    else must be a number (the same float64 values as ``float``)."""
    try:
        import pyarrow as pa
        import pyarrow.csv as pacsv
    except ImportError:
        return None
    names = [f"c{i}" for i in range(n_cols)]
    wanted = [names[i] for i in index]
    try:
        table = pacsv.read_csv(
            io.BytesIO(raw),
            read_options=pacsv.ReadOptions(column_names=names, skip_rows=1),
            parse_options=pacsv.ParseOptions(delimiter=","),
            convert_options=pacsv.ConvertOptions(
                include_columns=wanted, column_types=dict.fromkeys(wanted, pa.float64()),
                null_values=["", "nan", "NaN"], strings_can_be_null=False,
                quoted_strings_can_be_null=False))
    except (pa.ArrowException, ValueError):
        return None
    if table.num_rows == 0:
        return None
    out = np.empty((table.num_rows, len(wanted)))
    for j, name in enumerate(wanted):
        out[:, j] = table.column(name).to_numpy(zero_copy_only=False)
    return out


def _parse_fast(body: str, n_cols: int, index: list[int]) -> np.ndarray | None:
    """The wanted columns of the data rows via ``np.loadtxt``, or None if it cannot."""
    if not body.strip() or '"' in body:
        return None
    # Empty cells -> "nan" (twice: ",,," overlaps); then a leading or trailing empty cell.
    filled = body.replace(",,", ",nan,").replace(",,", ",nan,")
    filled = filled.replace(",\n", ",nan\n").replace(",\r", ",nan\r").replace("\n,", "\nnan,")
    if filled.startswith(","):
        filled = "nan" + filled
    if filled.endswith(","):
        filled += "nan"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values = np.loadtxt(
                io.StringIO(filled), delimiter=",", comments=None, dtype=np.float64, ndmin=2
            )
    except (ValueError, Warning):
        return None
    if values.shape[1] != n_cols:
        return None
    return values[:, index]


def _parse_slow(
    file: str, body: str, header: list[str], wanted: Sequence[str], index: list[int]
) -> tuple[np.ndarray, list[int]]:
    """Cell-by-cell parse of the data rows; raises on the first malformed row or cell.

    Returns the (R, len(wanted)) values and the file line number of each row.
    """
    reader = csv.reader(io.StringIO(body))
    n_cols = len(header)
    rows: list[list[float]] = []
    lines: list[int] = []
    for cells in reader:
        line = reader.line_num + 1  # + the header line
        if not cells:
            continue  # a blank line
        if len(cells) != n_cols:
            raise SessionError(
                f"{file}, line {line}: {len(cells)} cells, expected {n_cols} as in the header"
            )
        try:
            rows.append([_cell(cells[i]) for i in index])
        except ValueError:
            name, i = next((n, i) for n, i in zip(wanted, index) if not _is_cell(cells[i]))
            raise SessionError(
                f"{file}, line {line}, column {name!r}: expected a number (empty or nan for a "
                f"missing reading), got {cells[i]!r}"
            ) from None
        lines.append(line)
    values = np.array(rows, dtype=np.float64).reshape(len(rows), len(wanted))
    return values, lines


def _first_problem(values: np.ndarray, names: Sequence[str]) -> tuple[int, str] | None:
    """The earliest (row index, message tail) of an infinite cell, a missing or unordered t."""
    problems = []
    inf = np.isinf(values)
    if inf.any():
        row, col = divmod(int(np.argmax(inf)), values.shape[1])
        problems.append((row, (
            f", column {names[col]!r}: expected a finite number (empty or nan for a missing "
            f"reading), got {float(values[row, col])!r}"
        )))
    t = values[:, 0]
    nan_t = np.isnan(t)
    if nan_t.any():
        row = int(np.argmax(nan_t))
        problems.append((row, f", column {names[0]!r}: t is missing; every row needs its time (s)"))
    unordered = np.diff(t) <= 0.0  # False next to a NaN: that row is reported as missing
    if unordered.any():
        row = int(np.argmax(unordered)) + 1
        problems.append((row, (
            f": t = {float(t[row])!r} is not after the previous row's t = "
            f"{float(t[row - 1])!r}; t must be strictly increasing"
        )))
    return min(problems, default=None)


def _write_csv(file: str, header: Sequence[str], t: np.ndarray, values: np.ndarray,
               digits: int = 9) -> None:
    # One %-format per row (formatting runs in C); "%r" of a Python float is the shortest
    # string that reads back as the same float64. Only NaN prints as "nan" here, and no
    # number contains "nan", so the replace turns exactly the NaN cells into empty ones.
    if not 1 <= int(digits) <= 17:
        raise ValueError(f"write_session: digits must be 1..17, got {digits}")
    fmt = ",".join(["%r"] + [f"%.{int(digits)}g"] * values.shape[1])
    rows = np.column_stack([np.asarray(t, dtype=np.float64), values]).tolist()
    body = "\n".join([fmt % tuple(row) for row in rows]).replace("nan", "")
    with atomic_write(file, encoding="utf-8", newline="") as f:
        f.write(",".join(header) + "\n")
        if body:
            f.write(body + "\n")


def _write_columns(file: str, header: Sequence[str], t: np.ndarray, values: np.ndarray) -> None:
    """``t`` (float64) and ``values`` (float32 or float64, as computed) as CSV, each number as
    the shortest text that reads back as the same value of its own type, NaN an empty cell;
    whole or not at all. pyarrow's writer (several threads: 0.46 s for an hour of 6 angles
    against 1.6 s formatting row by row), else ``_write_csv`` at the type's full precision."""
    values = np.asarray(values)
    try:
        import pyarrow as pa
        import pyarrow.csv as pacsv
    except ImportError:
        digits = 9 if values.dtype == np.float32 else 17
        _write_csv(file, header, t, values, digits)
        return
    columns = [pa.array(np.asarray(t, np.float64), from_pandas=True)]
    columns += [pa.array(np.ascontiguousarray(values[:, j]), from_pandas=True)
                for j in range(values.shape[1])]
    table = pa.Table.from_arrays(columns, names=[f"c{j}" for j in range(len(columns))])
    with atomic_write(file, "wb") as f:
        f.write((",".join(header) + "\n").encode())
        pacsv.write_csv(table, f, write_options=pacsv.WriteOptions(include_header=False,
                                                                    quoting_style="none"))


def _cell(text: str) -> float:
    """One CSV cell: empty (or blank) is NaN, otherwise ``float`` (ValueError for text)."""
    return float(text) if text.strip() else math.nan


def _is_cell(text: str) -> bool:
    try:
        _cell(text)
    except ValueError:
        return False
    return True
