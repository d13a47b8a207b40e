"""The package's layout rules, checked on its source.

* No module imports a private name (``_x``) of another module.
* An import inside a function says why in a comment (an optional dependency, a heavy
  import, an import cycle), on its line or just above it.
* No function is longer than 150 lines, docstring included.
* No import cycle among the package's modules, counting imports inside functions.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pylensfit

SRC = Path(pylensfit.__file__).parent
MAX_LINES = 150
FUNCS = (ast.FunctionDef, ast.AsyncFunctionDef)


def _module(name: str, text: str):
    return name, text.splitlines(), ast.parse(text)


def _package():
    return [_module(p.relative_to(SRC).with_suffix("").as_posix().replace("/", "."),
                    p.read_text()) for p in sorted(SRC.rglob("*.py"))]  # fmt: skip


def private_imports(modules) -> list[str]:
    return [f"{name}: from {node.module} import {a.name}"
            for name, _, tree in modules for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom)
            for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]


def silent_local_imports(modules) -> list[str]:
    found = []
    for name, lines, tree in modules:
        for fn in (n for n in ast.walk(tree) if isinstance(n, FUNCS)):
            for node in ast.walk(fn):
                if not isinstance(node, (ast.Import, ast.ImportFrom)):
                    continue
                here = lines[node.lineno - 1]
                # a comment on the line, or on one of the two above it (a block of
                # imports from one optional package shares its comment)
                above = lines[max(node.lineno - 3, 0):node.lineno - 1]
                if "#" not in here and not any(s.strip().startswith("#") for s in above):
                    found.append(f"{name}:{node.lineno}: {here.strip()}")
    return found


def long_functions(modules) -> list[str]:
    return [f"{name}.{fn.name}: {fn.end_lineno - fn.lineno + 1} lines"
            for name, _, tree in modules for fn in ast.walk(tree)
            if isinstance(fn, FUNCS) and fn.end_lineno - fn.lineno + 1 > MAX_LINES]


def import_cycles(modules) -> list[tuple[str, str]]:
    """``(a, b)`` for every import of module ``b`` by ``a`` (relative, at any level of
    the code) where ``b`` imports ``a`` back, directly or through others."""
    deps: dict[str, set[str]] = {}
    for name, _, tree in modules:
        d = deps.setdefault(name, set())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                d |= {node.module.split(".")[0]} if node.module else {a.name for a in node.names}

    def reaches(a: str, b: str) -> bool:
        seen, todo = set(), [a]
        while todo:
            m = todo.pop()
            if m == b:
                return True
            if m not in seen:
                seen.add(m)
                todo += deps.get(m, ())
        return False

    return [(a, b) for a, ds in deps.items() for b in ds if b != a and reaches(b, a)]


def test_no_import_cycles():
    assert import_cycles(_package()) == []


def test_no_private_imports_across_modules():
    assert private_imports(_package()) == []


def test_function_level_imports_say_why():
    assert silent_local_imports(_package()) == []


def test_no_long_functions():
    assert long_functions(_package()) == []


def test_the_checks_find_what_they_are_for():
    bad = [_module("m", "from .x import _hidden, shown\n"
                        "def f():\n    import os\n    import sys  # start-up cost\n"
                        "    return os, sys\n"
                        "def g():\n" + "    pass\n" * MAX_LINES)]
    assert private_imports(bad) == ["m: from x import _hidden"]
    assert silent_local_imports(bad) == ["m:3: import os"]
    assert long_functions(bad) == [f"m.g: {MAX_LINES + 1} lines"]
    loop = [_module("a", "from .b import x\n"), _module("b", "def f():\n    from .a import y\n")]
    assert sorted(import_cycles(loop)) == [("a", "b"), ("b", "a")]
