"""OpenSim Storage motion capture (``mocap.mot`` or ``mocap.sto`` in place of ``mocap.csv``).

The text file OpenSim's inverse kinematics writes: free header lines, among them
``inDegrees=yes`` or ``inDegrees=no``, ending in a line ``endheader``; then a row of column
names whose first is ``time`` (s), then one row per frame, the cells separated by tabs (any
whitespace is accepted). Our angles are found by our names (``theta1_x``, ``phi_x``, ...) or
under the names ``meta.json``'s ``mocap_columns`` gives them; other columns are ignored.
Angles in degrees are converted to radians.

A header without ``inDegrees`` is refused rather than guessed: OpenSim's own ``.mot`` files
(inverse kinematics) are in degrees and many ``.sto`` files in radians, and a wrong guess is
a factor of 57 that the plausibility check catches only one way round.

As ``_csvio``: a fast path (``np.loadtxt``) for a well-formed file, and when anything is
wrong a cell-by-cell reading that names the line and the column. Plain NumPy and the
standard library, at the edge of the package.
"""

from __future__ import annotations

import io
import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from ._csvio import SessionError, _checked, _columns_for, _read_text

#: The Storage files that may hold a session's motion capture, in place of ``mocap.csv``.
STORAGE_FILES = ("mocap.mot", "mocap.sto")
_YES, _NO = ("yes", "true", "1"), ("no", "false", "0")


def read_storage(file: str, names: Sequence[str], mapping: Mapping[str, str],
                 context: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """The ``time`` column and our angles of an OpenSim Storage file.

    Args:
        file: the ``.mot`` or ``.sto`` file.
        names: our angle names, in the order wanted (``robot.angle_names``).
        mapping: our name -> the file's column name (``mocap_columns``; may be empty).
        context: what the robot is, for the message of a missing column.

    Returns:
        ``(time, angles, in_degrees)``: (F,) s, strictly increasing; (F, K) rad (NaN where the
        file says NaN); whether the header said ``inDegrees=yes`` (the plausibility checks
        name the header when its numbers look like the other unit).

    Raises:
        SessionError: no ``endheader``, no or a bad ``inDegrees``, a first column that is not
            ``time``, an angle that matches no column, a duplicated column, a bad cell, a row
            of the wrong length, a ``time`` that is missing or goes back; one line naming the
            file, the line and the column.
    """
    lines = _read_text(file).splitlines()
    end = next((i for i, line in enumerate(lines) if line.strip().lower() == "endheader"), None)
    if end is None:
        raise SessionError(
            f"{file}: no 'endheader' line; an OpenSim Storage file has a header ending in a "
            "line 'endheader', then a row of column names starting with 'time', then the rows")
    in_degrees = _in_degrees(file, lines[:end])
    first = next((i for i in range(end + 1, len(lines)) if lines[i].strip()), None)
    if first is None:
        raise SessionError(f"{file}, line {end + 1}: expected a row of column names after "
                           "'endheader', got none")
    row = lines[first]
    header = [c.strip() for c in row.split("\t")] if "\t" in row else row.split()
    while header and not header[-1]:
        header.pop()
    if header[0].lower() != "time":
        raise SessionError(
            f"{file}, line {first + 1}: the first column is {header[0]!r}, expected 'time' "
            "(s), as OpenSim writes it")
    wanted = [header[0], *_columns_for(file, names, header, mapping, context)]
    for name in dict.fromkeys(wanted):
        if header.count(name) > 1:
            raise SessionError(f"{file}, line {first + 1}: column {name!r} appears more than once")
    index = [header.index(n) for n in wanted]
    body = lines[first + 1:]
    values = _checked(file, _parse_fast(body, len(header), index), wanted,
                      f"no data rows after the column names (line {first + 1})",
                      lambda: _parse_slow(file, body, first + 2, header, wanted, index))
    angles = values[:, 1:]
    if in_degrees:
        angles = angles * (math.pi / 180.0)
    return np.ascontiguousarray(values[:, 0]), np.ascontiguousarray(angles), in_degrees


def _in_degrees(file: str, header: list[str]) -> bool:
    for i, line in enumerate(header):
        key, sep, value = line.partition("=")
        if sep and key.strip().lower() == "indegrees":
            flag = value.strip().lower()
            if flag not in _YES + _NO:
                raise SessionError(
                    f"{file}, line {i + 1}: inDegrees={value.strip()!r}, expected yes or no")
            return flag in _YES
    raise SessionError(
        f"{file}: no 'inDegrees=yes' or 'inDegrees=no' line before 'endheader', so the angles' "
        "unit is unknown; add the one that is true to the header (OpenSim's inverse "
        "kinematics writes inDegrees=yes)")


def _parse_fast(body: list[str], n_cols: int, index: list[int]) -> np.ndarray | None:
    """The wanted columns of the rows via ``np.loadtxt`` (blank lines skipped), or None."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values = np.loadtxt(io.StringIO("\n".join(body)), comments=None, dtype=np.float64,
                                ndmin=2)
    except (ValueError, Warning):
        return None
    if values.shape[0] == 0 or values.shape[1] != n_cols:
        return None
    return values[:, index]


def _parse_slow(file: str, body: list[str], first_line: int, header: list[str],
                wanted: list[str], index: list[int]) -> tuple[np.ndarray, list[int]]:
    """Cell by cell; raises on the first short row or bad cell. Returns the (R, len(wanted))
    values and the file line number of each row."""
    rows: list[list[float]] = []
    numbers: list[int] = []
    for line, text in enumerate(body, start=first_line):
        cells = text.split()
        if not cells:
            continue
        if len(cells) != len(header):
            raise SessionError(f"{file}, line {line}: {len(cells)} cells, expected "
                               f"{len(header)} as in the column names")
        for name, i in zip(wanted, index):
            try:
                float(cells[i])
            except ValueError:
                raise SessionError(
                    f"{file}, line {line}, column {name!r}: expected a number (NaN for a "
                    f"missing frame), got {cells[i]!r}") from None
        rows.append([float(cells[i]) for i in index])
        numbers.append(line)
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(wanted)), numbers
