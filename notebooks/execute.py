"""Run the notebooks and store them with their outputs, without Jupyter.

    python notebooks/execute.py [NAME ...]        # every notebook here when none is named
    python notebooks/execute.py --output PATH NAME

``NAME``: ``01_tour``, ``01_tour.ipynb`` or a path to a notebook. Each notebook runs as a user
runs it: a fresh Python process (the environment as given: no XLA flag is set here), its code
cells in order in one namespace, matplotlib's Agg backend, a temporary working directory (what
a notebook writes never lands in the repository). Each cell's outputs are what Jupyter shows:

* what it prints (``stdout``) as a ``stream`` output;
* the value of its last line when that is an expression (not ``None``, not a figure, not
  silenced by a trailing ``;``) as an ``execute_result``, its ``repr``;
* every matplotlib figure open at its end, or at a ``plt.show()``, as a ``display_data``
  output: a PNG at ``DPI`` dots per inch in 256 colours (base64) and the figure's ``repr``;
  the figures are then closed.

What a cell writes to stderr (warnings, progress) goes to the terminal and is not stored. A
cell that raises stops the run, and the notebook is left as it was. The notebook is rewritten
in place as nbformat 4.5 JSON (its metadata and markdown kept, every cell given a stable
``id``, keys sorted, indent 1: the way Jupyter writes it, so diffs stay small); with
``--output`` (one notebook) it is written to ``PATH`` instead, which ``tests/test_notebooks.py``
uses to check that the stored outputs are current.
"""

from __future__ import annotations

import argparse
import ast
import base64
import contextlib
import hashlib
import io
import json
import linecache
import os
import subprocess
import sys
import tempfile
import time

from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
#: The figures' resolution: about a notebook's width in a browser for a 9-inch figure.
DPI = 80


def notebook_path(name: str) -> str:
    """``name`` (``01_tour``, ``01_tour.ipynb`` or a path) as the path of a notebook."""
    if os.path.exists(name):
        return os.path.abspath(name)
    path = os.path.join(HERE, name if name.endswith(".ipynb") else f"{name}.ipynb")
    if not os.path.exists(path):
        raise SystemExit(f"execute.py: no notebook {name!r} (looked for {path})")
    return path


def lines(text: str) -> list[str]:
    """A multi-line string as nbformat stores it: a list of lines, each with its newline."""
    return text.splitlines(keepends=True)


def source_of(cell: dict) -> str:
    src = cell["source"]
    return src if isinstance(src, str) else "".join(src)


def cell_id(cell: dict, taken: set[str]) -> str:
    """The cell's ``id``: the one it has, else one from its type and source (stable from then
    on, as it is stored), unique in the notebook."""
    cid = cell.get("id")
    if not cid:
        digest = hashlib.sha1((cell["cell_type"] + source_of(cell)).encode()).hexdigest()
        cid = digest[:8]
    base, n = cid, 1
    while cid in taken:
        cid, n = f"{base}-{n}", n + 1
    taken.add(cid)
    return cid


def png(fig) -> bytes:
    """``fig`` as a PNG of at most 256 colours (Pillow, which matplotlib needs: a third to
    half the bytes of matplotlib's true-colour PNG of a figure of many lines)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight", metadata={"Software": None})
    image = Image.open(io.BytesIO(buf.getvalue())).convert("RGB")
    buf = io.BytesIO()
    image.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(buf, "PNG", optimize=True)
    return buf.getvalue()


class Cell:
    """One code cell's outputs, in the order they appear."""

    def __init__(self, plt, count: int):
        self.plt, self.count, self.outputs = plt, count, []
        self.stdout = io.StringIO()

    def flush_stdout(self) -> None:
        text = self.stdout.getvalue()
        self.stdout.seek(0)
        self.stdout.truncate()
        if not text:
            return
        last = self.outputs[-1] if self.outputs else None
        if last is not None and last["output_type"] == "stream" and last["name"] == "stdout":
            last["text"] = lines("".join(last["text"]) + text)
        else:
            self.outputs.append({"name": "stdout", "output_type": "stream", "text": lines(text)})

    def show_figures(self) -> None:
        """Every open figure as a ``display_data`` output, then closed."""
        self.flush_stdout()
        for num in self.plt.get_fignums():
            fig = self.plt.figure(num)
            self.outputs.append({
                "data": {"image/png": base64.b64encode(png(fig)).decode("ascii"),
                         "text/plain": lines(repr(fig))},
                "metadata": {}, "output_type": "display_data"})
        self.plt.close("all")

    def result(self, value) -> None:
        self.flush_stdout()
        self.outputs.append({"data": {"text/plain": lines(repr(value))},
                             "execution_count": self.count, "metadata": {},
                             "output_type": "execute_result"})


def run_cells(nb: dict, label: str) -> dict:
    """``nb`` with every code cell run in order in one namespace, its outputs and execution
    count set (this process: the child ``main`` starts)."""
    import matplotlib  # here, not above: the parent never needs it, and Agg comes first

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    namespace = {"__name__": "__main__"}
    current: list[Cell] = []
    plt.show = lambda *args, **kwargs: current[-1].show_figures()  # Jupyter shows them here
    count, taken = 0, set()
    for i, cell in enumerate(nb["cells"]):
        cell["id"] = cell_id(cell, taken)
        if isinstance(cell.get("source"), str):
            cell["source"] = lines(cell["source"])
        if cell["cell_type"] != "code":
            continue
        count += 1
        out = Cell(plt, count)
        current.append(out)
        source = source_of(cell)
        filename = f"{label}[cell {i}]"
        linecache.cache[filename] = (len(source), None, lines(source), filename)  # tracebacks
        tree = ast.parse(source, filename)
        last = tree.body.pop() if tree.body and isinstance(tree.body[-1], ast.Expr) else None
        start = time.perf_counter()
        with contextlib.redirect_stdout(out.stdout):
            exec(compile(tree, filename, "exec"), namespace)
            value = (None if last is None else
                     eval(compile(ast.Expression(last.value), filename, "eval"), namespace))
        if value is not None and not isinstance(value, Figure) \
                and not source.rstrip().endswith(";"):
            out.result(value)
        out.show_figures()
        print(f"{label} cell {i} [{count}]: {time.perf_counter() - start:.1f} s",
              file=sys.stderr, flush=True)
        cell["outputs"], cell["execution_count"] = out.outputs, count
    nb["nbformat"], nb["nbformat_minor"] = 4, max(5, nb.get("nbformat_minor", 5))
    return nb


def dumps(nb: dict) -> str:
    """nbformat's own layout: keys sorted, indent 1, UTF-8 as is, a final newline."""
    return json.dumps(nb, sort_keys=True, indent=1, ensure_ascii=False) + "\n"


def execute(path: str, output: str) -> None:
    """Run the notebook at ``path`` in a fresh process in a temporary folder and write it,
    with its outputs, to ``output`` (which may be ``path``); leave ``output`` as it was if a
    cell raises."""
    with tempfile.TemporaryDirectory(prefix="kckf-notebook-") as work:
        fresh = os.path.join(work, ".executed.ipynb")
        r = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", path, fresh],
                           cwd=work)
        if r.returncode != 0:
            raise SystemExit(f"execute.py: {os.path.basename(path)} failed (above); "
                             "left as it was")
        with open(fresh, encoding="utf-8") as f:
            text = f.read()
    part = output + ".part"
    with open(part, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(part, output)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="notebooks (default: every one here)")
    parser.add_argument("--output", help="write the executed notebook here (one notebook)")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:  # the fresh process: run the cells, write the result
        src, dst = args.child
        sys.path[0] = ""  # as `python -c` and a kernel have it, not this folder
        with open(src, encoding="utf-8") as f:
            nb = json.load(f)
        nb = run_cells(nb, os.path.basename(src))
        with open(dst, "w", encoding="utf-8") as f:
            f.write(dumps(nb))
        return
    names = args.names or sorted(f for f in os.listdir(HERE) if f.endswith(".ipynb"))
    if args.output and len(names) != 1:
        parser.error("--output takes one notebook")
    for name in names:
        path = notebook_path(name)
        start = time.perf_counter()
        execute(path, os.path.abspath(args.output) if args.output else path)
        print(f"{os.path.basename(path)}: executed in {time.perf_counter() - start:.0f} s, "
              f"{os.path.getsize(args.output or path) / 1000:.0f} kB", file=sys.stderr)


if __name__ == "__main__":
    main()
