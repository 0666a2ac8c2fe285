"""The notebooks are stored executed, and what they show is current: each runs from top to
bottom as a user runs it (``notebooks/execute.py``: a fresh Python process, its code cells in
order in one namespace, compiled with XLA's default flags; the other tests compile with
conftest.py's faster-compiling ones), and the stored notebook must show what the fresh run
shows: output on every cell that has some, a figure wherever the run makes one, and the same
printed text, its numbers to a tolerance (they move in their last digits between JAX versions
and machines). The figures' pixels are not compared."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest
from helpers import default_compile_env

NOTEBOOKS = os.path.join(os.path.dirname(__file__), "..", "notebooks")
EXECUTE = os.path.join(NOTEBOOKS, "execute.py")

#: A number standing alone (not a digit of a name such as ``theta1_x``), with its sign, as
#: far as its last digit: ``-4.8``, ``2.507e+05``, ``12`` (a unit may follow: ``12ms``).
NUMBER = re.compile(r"(?<![\w.])[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?!\.?\d)")
#: An object's address in a ``repr``: never the same twice.
ADDRESS = re.compile(r"0x[0-9a-fA-F]+")
#: Two printed decimals agree within the larger of these, or one unit of their last digit.
REL, ABS = 0.02, 0.02


def same_number(a: str, b: str) -> bool:
    """Integers exactly; decimals within ``REL`` or ``ABS``, whichever is larger, or one unit
    in the last place printed (``4.85`` printed as ``-4.8`` in one run and ``-4.9`` in the
    other)."""
    if not re.search(r"[.eE]", a + b):
        return int(a) == int(b)
    x, y = float(a), float(b)
    places = max(len(m.group(1)) if (m := re.search(r"\.(\d+)", s)) else 0 for s in (a, b))
    exp = min(int(m.group(1)) if (m := re.search(r"[eE]([-+]?\d+)", s)) else 0 for s in (a, b))
    ulp = 10.0 ** (exp - places)
    return abs(x - y) <= max(ABS, REL * max(abs(x), abs(y)), ulp * 1.000001)


def same_line(stored: str, fresh: str) -> bool:
    """The same words in the same order (spacing aside: a wider number moves the columns), and
    the same numbers as ``same_number`` has it."""
    stored, fresh = ADDRESS.sub("0x?", stored), ADDRESS.sub("0x?", fresh)
    a, b = NUMBER.findall(stored), NUMBER.findall(fresh)
    words = [re.sub(r"\s+", "", w) for w in NUMBER.split(stored)]
    if words != [re.sub(r"\s+", "", w) for w in NUMBER.split(fresh)] or len(a) != len(b):
        return False
    return all(same_number(x, y) for x, y in zip(a, b))


def printed(cell: dict) -> list[str]:
    """The text a code cell shows: what it printed and the value of its last line."""
    text = []
    for out in cell.get("outputs", []):
        if out["output_type"] == "stream" and out["name"] == "stdout":
            text.append("".join(out["text"]))
        elif out["output_type"] == "execute_result":
            text.append("".join(out["data"].get("text/plain", "")) + "\n")
    return "".join(text).splitlines()


def figures(cell: dict) -> int:
    return sum("image/png" in out.get("data", {}) for out in cell.get("outputs", []))


def differences(stored: dict, fresh: dict) -> list[str]:
    """Where the stored notebook does not show what the fresh run of it shows."""
    found = []
    cells = [(i, s, f) for i, (s, f) in enumerate(zip(stored["cells"], fresh["cells"]))
             if f["cell_type"] == "code"]
    for i, s, f in cells:
        where = f"cell {i} ([{f['execution_count']}] in Jupyter)"
        if s.get("execution_count") is None:
            found.append(f"{where}: not executed")
        if f["outputs"] and not s.get("outputs"):
            found.append(f"{where}: no output stored; a fresh run shows some")
            continue
        if figures(s) != figures(f):
            found.append(f"{where}: {figures(s)} figure(s) stored, a fresh run makes "
                         f"{figures(f)}")
        a, b = printed(s), printed(f)
        if len(a) != len(b):
            found.append(f"{where}: {len(a)} printed line(s) stored, a fresh run prints "
                         f"{len(b)}")
        else:
            bad = [(x, y) for x, y in zip(a, b) if not same_line(x, y)]
            if bad:
                found.append(f"{where}: stored {bad[0][0]!r}, a fresh run prints {bad[0][1]!r}"
                             + (f" (and {len(bad) - 1} more line(s))" if len(bad) > 1 else ""))
    return found


@pytest.mark.parametrize("name", sorted(f for f in os.listdir(NOTEBOOKS) if f.endswith(".ipynb")))
@pytest.mark.long
def test_notebook_is_stored_executed_and_current(name, tmp_path):
    fresh_path = tmp_path / name
    r = subprocess.run([sys.executable, EXECUTE, "--output", str(fresh_path),
                        os.path.abspath(os.path.join(NOTEBOOKS, name))],
                       cwd=tmp_path, capture_output=True, text=True, timeout=280,
                       env=default_compile_env())
    assert r.returncode == 0, r.stderr[-3000:]
    with open(os.path.join(NOTEBOOKS, name), encoding="utf-8") as f:
        stored = json.load(f)
    with open(fresh_path, encoding="utf-8") as f:
        fresh = json.load(f)
    def sources(nb):
        return ["".join(c["source"]) for c in nb["cells"]]

    assert sources(stored) == sources(fresh)
    found = differences(stored, fresh)
    stem = name.removesuffix(".ipynb")
    assert not found, (f"notebooks/{name} does not show what it shows when run: "
                       + "; ".join(found)
                       + f". Run `python notebooks/execute.py {stem}` and commit the result.")


@pytest.mark.parametrize("stored, fresh, same", [
    ("mean  paper   1.54   fitted   0.38 deg", "mean  paper   1.55   fitted   0.39 deg", True),
    ("rmse 0.380", "rmse 0.405", False),  # 0.025: beyond 0.02 and 2 %
    ("clock -4.8 ms", "clock -4.9 ms", True),  # one unit in the last place
    ("clock -4.8 ms", "clock -5.0 ms", False),
    ("q  43033.1", "q 43900.0", True),  # 2 %
    ("c=2.507e+05", "c=2.550e+05", True),
    ("best step 40", "best step 30", False),  # integers exactly
    ("theta1_x 0.30", "theta2_x 0.30", False),  # a name's digits are a name's
    ("paper   9.99 x", "paper  10.01 x", True),  # spacing aside
    ("<Figure at 0x7f3a>", "<Figure at 0x55b1>", True),
    ("white", "not white", False),
])
def test_printed_lines_compare_numbers_to_a_tolerance(stored, fresh, same):
    assert same_line(stored, fresh) is same
