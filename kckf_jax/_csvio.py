"""The CSV files of a session (``sensors.csv``, ``mocap.csv``): read fast, and when anything is
wrong, read again cell by cell to name the line and the column; written back at full precision.

Plain NumPy and the standard library, at the edge of the package.
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections.abc import Sequence

import numpy as np

META_FILE = "meta.json"
SENSORS_FILE = "sensors.csv"
MOCAP_FILE = "mocap.csv"


class SessionError(ValueError):
    """A malformed session, in one user-facing line.

    The message names the file, the row (its line number in the file, the header being line 1)
    and/or the column, what was found and what was expected.
    """


def _read_text(file: str) -> str:
    try:
        with open(file, encoding="utf-8-sig", newline="") as f:
            return f.read()
    except FileNotFoundError:
        raise SessionError(
            f"{file}: file not found (a session folder holds {META_FILE}, {SENSORS_FILE} "
            f"and optionally {MOCAP_FILE})"
        ) from None
    except UnicodeDecodeError as e:
        raise SessionError(f"{file}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    except OSError as e:
        raise SessionError(f"{file}: cannot read ({e.strerror})") from None


def _read_csv(
    file: str, required: Sequence[str], optional: Sequence[str], context: str
) -> dict[str, np.ndarray]:
    """The ``required`` and present ``optional`` columns of a CSV file as float64 arrays.

    Blank lines are skipped; an empty cell or ``nan`` is NaN; ``t`` (the first required
    column) must be present in every row, finite and strictly increasing; no cell may be
    infinite or text. A fast path (``np.loadtxt``) reads well-formed files; anything it cannot
    read, or any problem in what it read, is read again cell by cell to report the first
    problem with its line number.
    """
    text = _read_text(file)
    header_line, _, body = text.partition("\n")
    header = [name.strip() for name in next(csv.reader([header_line.rstrip("\r")]), [])]
    if not any(header):
        raise SessionError(f"{file}, line 1: expected a header row of column names, got none")
    wanted = (*required, *(n for n in optional if n in header))
    missing = [n for n in required if n not in header]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise SessionError(f"{file}: missing column {missing[0]!r}{more} ({context})")
    for name in wanted:
        if header.count(name) > 1:
            raise SessionError(f"{file}, line 1: column {name!r} appears more than once")
    index = [header.index(n) for n in wanted]

    values = _parse_fast(body, len(header), index)
    if values is None or _first_problem(values, wanted) is not None:
        values, lines = _parse_slow(file, body, header, wanted, index)
        if not lines:
            raise SessionError(f"{file}: no data rows after the header line")
        problem = _first_problem(values, wanted)
        if problem is not None:
            row, message = problem
            raise SessionError(f"{file}, line {lines[row]}{message}")
    return {name: np.ascontiguousarray(values[:, j]) for j, name in enumerate(wanted)}


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
    with open(file, "w", encoding="utf-8", newline="") as f:
        f.write(",".join(header) + "\n")
        if body:
            f.write(body + "\n")


def _cell(text: str) -> float:
    """One CSV cell: empty (or blank) is NaN, otherwise ``float`` (ValueError for text)."""
    return float(text) if text.strip() else math.nan


def _is_cell(text: str) -> bool:
    try:
        _cell(text)
    except ValueError:
        return False
    return True
