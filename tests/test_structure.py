"""The package's shape (docs/architecture.md): no import circle, modules of one concept, the
public API listed where a reader starts, recipes on the public API only."""

from __future__ import annotations

import ast
import os
import re
from pathlib import Path

import kckf_jax

PKG = os.path.dirname(kckf_jax.__file__)
ROOT = os.path.dirname(PKG)
#: The repository (this file's parent's parent): ``ROOT`` is site-packages where the package
#: is installed, not linked, as CI installs it.
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _modules() -> dict[str, str]:
    """``{dotted module name: file}`` for every module of the package."""
    out = {}
    for folder, _, files in os.walk(PKG):
        for f in files:
            if f.endswith(".py"):
                rel = os.path.relpath(os.path.join(folder, f), ROOT)[:-3].replace(os.sep, ".")
                out[rel.removesuffix(".__init__")] = os.path.join(folder, f)
    return out


def _imports(name: str, file: str, modules: dict[str, str]) -> set[str]:
    """The package modules ``name`` imports (at any depth of its code, lazy imports too)."""
    tree = ast.parse(Path(file).read_text())
    package = name if file.endswith("__init__.py") else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            for alias in node.names:
                full = f"{target}.{alias.name}"
                found.add(full if full in modules else target)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in modules and m != name}


def test_no_import_circle():
    modules = _modules()
    graph = {m: _imports(m, f, modules) for m, f in modules.items()}
    # Edges into a package are edges into its __init__ (which re-exports its modules), so a
    # module that imports its own package from below would show up as a circle.
    state: dict[str, int] = {}

    def visit(m, trail):
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                raise AssertionError("import circle: " + " -> ".join(trail[trail.index(n):]
                                                                      + [n]))
            if state.get(n) is None:
                visit(n, trail + [n])
        state[m] = 2

    for m in sorted(graph):
        if state.get(m) is None:
            visit(m, [m])


def test_the_kernel_imports_no_path_and_filters_no_simulator():
    modules = _modules()
    kernel = _imports("kckf_jax._models._kernel", modules["kckf_jax._models._kernel"], modules)
    assert not any(m.startswith("kckf_jax._paths") for m in kernel), kernel
    for system in ("arm_imu", "markov"):
        name = f"kckf_jax.filters.{system}._filter"
        assert not any(m.endswith("_sim") or m.endswith("_experiment")
                       for m in _imports(name, modules[name], modules))


def test_modules_are_one_concept_long():
    for name, file in _modules().items():
        n = len(Path(file).read_text().splitlines())
        assert n <= 600, f"{name}: {n} lines"


def test_init_docstring_lists_every_public_name():
    doc = kckf_jax.__doc__
    public = [n for n in dir(kckf_jax) if not n.startswith("_") and n not in ("filters", "cli",
                                                                            "plots",
                                                                            "export_loader")]
    public = [n for n in public if not isinstance(getattr(kckf_jax, n), type(os))]
    missing = [n for n in public if f"``{n}``" not in doc]
    assert not missing, missing


#: What a benchmark may reach below the public API (the state's block layout and the paper's
#: matrices, to build a peer's model): nothing else, and training and notebooks nothing.
BENCHMARK_INTERNALS = re.compile(
    r"from kckf_jax\._models\._blocks import (full_state|paper_matrices|structure)(, (full_state|"
    r"paper_matrices|structure))*\b")


def test_recipes_benchmarks_and_notebooks_use_the_public_api():
    pattern = re.compile(r"kckf_jax(\.filters)?\._[a-z]")
    for folder in ("training", "benchmarks", "notebooks"):
        assert os.path.isdir(os.path.join(REPO, folder)), folder  # never passed on nothing
        for dirpath, _, files in os.walk(os.path.join(REPO, folder)):
            for f in files:
                if f.endswith((".py", ".ipynb")):
                    text = Path(dirpath, f).read_text()
                    if folder == "benchmarks":
                        text = BENCHMARK_INTERNALS.sub("", text)
                    assert not pattern.search(text), f"{folder}/{f} imports a private module"


def test_public_functions_take_and_return_public_types():
    """Every kckf_jax class a public function's or class's signature names is exported."""
    import inspect
    import typing

    exported = {id(v) for v in vars(kckf_jax).values()}
    missing = set()
    for name in dir(kckf_jax):
        obj = getattr(kckf_jax, name)
        if name.startswith("_") or not callable(obj):
            continue
        targets = [obj] + ([getattr(obj, m) for m, v in vars(obj).items()
                            if callable(v) and not m.startswith("_")]
                           if isinstance(obj, type) else [])
        for fn in targets:
            try:
                hints = typing.get_type_hints(fn)
            except Exception:  # noqa: BLE001 (a forward reference the module does not bind)
                hints = getattr(fn, "__annotations__", {})
            for hint in hints.values():
                for t in _types_in(hint):
                    mod = getattr(t, "__module__", "")
                    if mod.startswith("kckf_jax") and inspect.isclass(t) and id(t) not in exported:
                        missing.add(f"{name}: {t.__module__}.{t.__qualname__}")
    assert not missing, sorted(missing)


def _types_in(hint):
    import typing

    yield hint
    for arg in typing.get_args(hint):
        yield from _types_in(arg)


def test_the_top_level_shows_the_folders():
    """``kckf_jax/`` holds the public face and the concept folders (docs/architecture.md),
    at most a dozen entries: a new module goes into the folder of its concept. (``_data``:
    the sample sessions an installed wheel carries, ``pyproject.toml``.)"""
    entries = sorted(n for n in os.listdir(PKG)
                     if n not in ("__pycache__", "_data") and not n.startswith("."))
    assert len(entries) <= 12, entries
    loose = [n for n in entries if n.endswith(".py")]
    assert loose == ["__init__.py", "__main__.py", "export_loader.py"], loose
