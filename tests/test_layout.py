"""The packages' layout rules, checked on their source.

Each rule holds for the method (``pylensfit``) and for the validation harness
(``pylensfit_validation``):

* No module imports a private name (``_x``) of another module.
* An import inside a function says why in a comment (an optional dependency, a heavy
  import, an import cycle), on its line or just above it.
* No function is longer than 150 lines, docstring included (80 in the method).
* No import cycle among the package's modules, counting imports inside functions.
* No module of the method imports one of a higher layer (:data:`LAYERS`).
* No numba kernel of the method takes more than :data:`MAX_KERNEL_ARGS` arguments.

And between the layers:

* No module of the method imports the harness.
* The harness and the benchmarks (``benchmarks/``, ``benchmarks/studies/``) use of the
  method only the names it exports: those of ``pylensfit.__all__`` and of the
  ``__all__`` of the public modules, :data:`PUBLIC_MODULES`, each documented in
  ``docs/api.rst``.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import types
from pathlib import Path

import pytest

import pylensfit
import pylensfit_validation

SRC = Path(pylensfit.__file__).parent
HARNESS = Path(pylensfit_validation.__file__).parent
ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = (ROOT / "benchmarks", ROOT / "benchmarks" / "studies")
PACKAGES = {"pylensfit": SRC, "pylensfit_validation": HARNESS}
MAX_LINES = 150
#: The method's functions are shorter still (docstring included).
MAX_METHOD_LINES = 80
FUNCS = (ast.FunctionDef, ast.AsyncFunctionDef)

#: The method's public modules: what they export (``__all__``) may be used by the harness,
#: the benchmarks and users; each is documented in docs/api.rst.
PUBLIC_MODULES = (
    "pylensfit",
    "pylensfit.calibration",
    "pylensfit.catalogue",
    "pylensfit.cli",
    "pylensfit.config",
    "pylensfit.detection",
    "pylensfit.exposures",
    "pylensfit.flags",
    "pylensfit.forced",
    "pylensfit.grid",
    "pylensfit.images",
    "pylensfit.joint",
    "pylensfit.likelihood",
    "pylensfit.metacal",
    "pylensfit.models",
    "pylensfit.pipeline",
    "pylensfit.prior",
    "pylensfit.psf",
    "pylensfit.psfmodel",
    "pylensfit.runner",
    "pylensfit.shear",
    "pylensfit.skyframe",
    "pylensfit.stamps",
    "pylensfit.weights",
)


def _module(name: str, text: str):
    return name, text.splitlines(), ast.parse(text)


def _package(src: Path = SRC):
    return [_module(p.relative_to(src).with_suffix("").as_posix().replace("/", "."),
                    p.read_text()) for p in sorted(src.rglob("*.py"))]  # fmt: skip


def _scripts():
    """The benchmark scripts, named by their path from the repository's root."""
    return [_module(p.relative_to(ROOT).as_posix(), p.read_text())
            for d in BENCHMARKS for p in sorted(d.glob("*.py"))]  # fmt: skip


def _exports() -> dict[str, set[str]]:
    return {m: set(importlib.import_module(m).__all__) for m in PUBLIC_MODULES}


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


def long_functions(modules, limit: int = MAX_LINES) -> list[str]:
    return [f"{name}.{fn.name}: {fn.end_lineno - fn.lineno + 1} lines"
            for name, _, tree in modules for fn in ast.walk(tree)
            if isinstance(fn, FUNCS) and fn.end_lineno - fn.lineno + 1 > limit]


def _resolve(name: str, node: ast.ImportFrom, known: set[str]) -> list[str]:
    """The modules of the package that the relative import ``node`` of module ``name``
    reaches (a package as its ``__init__``)."""
    pkg = name.split(".")[:-1]
    base = pkg[: len(pkg) - (node.level - 1)] if node.level > 1 else pkg
    wanted = ([base + node.module.split(".")] if node.module
              else [base + [a.name] for a in node.names])  # fmt: skip
    found = []
    for parts in wanted:
        for cand in (".".join(parts), ".".join(parts + ["__init__"]),
                     ".".join(parts[:-1] + ["__init__"])):  # fmt: skip
            if cand in known:
                found.append(cand)
                break
    return found


def dependencies(modules) -> dict[str, set[str]]:
    """``{module: modules of the package it imports}``, relative imports at any level of
    the code, submodules of subpackages by their dotted names."""
    known = {name for name, _, _ in modules}
    deps: dict[str, set[str]] = {}
    for name, _, tree in modules:
        d = deps.setdefault(name, set())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level >= 1:
                d |= set(_resolve(name, node, known)) - {name}
    return deps


def import_cycles(modules) -> list[tuple[str, str]]:
    """``(a, b)`` for every import of module ``b`` by ``a`` (relative, at any level of
    the code) where ``b`` imports ``a`` back, directly or through others."""
    deps = dependencies(modules)

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


#: The method's layers, from the bottom: a module imports only from its own layer or
#: from those below it (a subpackage counts as one module). The fit takes the priors
#: as its inputs, so the prior distributions lie below it; the Bayesian layer (shapes,
#: shear, weights, the measured response) lies above it, the assembly of catalogue rows
#: and the calibration recipe above that, the image pipeline above all of the method,
#: and the command line and the package's namespace on top.
LAYERS = (
    ("_version", "_util", "flags", "bankruns", "config", "runner"),
    ("grid", "_kernels_nb", "psf", "psfmodel", "detection", "stamps", "skyframe",
     "exposures", "catalogue"),
    ("models", "forced"),
    ("prior",),
    ("likelihood", "joint", "joint_nb"),
    ("shear", "weights", "metacal"),
    ("assemble",),
    ("calibration",),
    ("images", "pipeline"),
    ("cli", "__init__"),
)


def layer_violations(modules, layers=LAYERS) -> list[str]:
    """``"a -> b"`` for every import by ``a`` of a module ``b`` of a higher layer, and
    ``"a: no layer"`` for a top-level module that :data:`LAYERS` does not place."""
    rank = {m: i for i, layer in enumerate(layers) for m in layer}
    top = lambda m: m.split(".")[0]  # noqa: E731
    found = [f"{top(a)}: no layer" for a in dependencies(modules) if top(a) not in rank]
    for a, ds in dependencies(modules).items():
        found += [f"{a} -> {b}" for b in ds
                  if top(b) in rank and top(a) in rank and rank[top(b)] > rank[top(a)]]  # fmt: skip
    return sorted(set(found))


#: the most arguments a numba kernel of the method takes: a kernel's inputs come in
#: bundles (named tuples of arrays, as ngmix passes structured arrays)
MAX_KERNEL_ARGS = 10


def _imported(package: str, src: Path) -> list[types.ModuleType]:
    """Every module of the package ``package`` (its files under ``src``), imported."""
    names = [name.removesuffix(".__init__").removesuffix("__init__")
             for name, _, _ in _package(src)]  # fmt: skip
    return [importlib.import_module(f"{package}.{n}".rstrip(".")) for n in names]


def wide_kernels(modules: list[types.ModuleType], limit: int = MAX_KERNEL_ARGS) -> list[str]:
    """``"module.kernel: n arguments"`` for every numba dispatcher defined at the top level
    of one of ``modules`` (its ``py_func`` from that module) that takes more than
    ``limit`` arguments."""
    found = []
    for mod in modules:
        for name, obj in vars(mod).items():
            fn = getattr(obj, "py_func", None)
            if fn is None or getattr(fn, "__module__", None) != mod.__name__:
                continue
            n = len(inspect.signature(fn).parameters)
            if n > limit:
                found.append(f"{mod.__name__}.{name}: {n} arguments")
    return sorted(found)


def _absolute_imports(tree):
    """``(node, module)`` for every absolute import (``import m``, ``from m import ...``)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from ((node, a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node, node.module


def harness_imports(modules, harness: str = "pylensfit_validation") -> list[str]:
    """Every import of the harness (``harness``) by a module of ``modules``, at any level
    of the code."""
    return [f"{name}:{node.lineno}: {lines[node.lineno - 1].strip()}"
            for name, lines, tree in modules for node, mod in _absolute_imports(tree)
            if mod.split(".")[0] == harness]  # fmt: skip


def _dotted(node) -> list[str] | None:
    """``["a", "b", "c"]`` for the expression ``a.b.c``, None for anything else."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    return [node.id, *reversed(parts)] if isinstance(node, ast.Name) else None


def _unexported(module: str, names: list[str], exports: dict[str, set[str]]) -> str | None:
    """The first of ``names`` (a chain of attributes of ``module``) that the public
    modules of ``exports`` do not export, as ``module.name``; None if all are."""
    for name in names:
        if name.startswith("__") and name.endswith("__"):
            return None
        sub = f"{module}.{name}"
        if sub in exports:  # a public module, as an attribute of its package
            module = sub
            continue
        return None if name in exports.get(module, ()) else sub
    return None


def unexported_uses(modules, exports: dict[str, set[str]], method: str = "pylensfit"):
    """Every name of the package ``method`` that a module of ``modules`` imports or reads
    as an attribute but that no public module (``exports``: module -> its ``__all__``)
    exports, and every import of a module of ``method`` that is not public."""
    found = []
    for name, _, tree in modules:
        alias: dict[str, str] = {}
        for node, mod in _absolute_imports(tree):
            if mod.split(".")[0] != method:
                continue
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] != method:
                        continue
                    top = a.name if a.asname else method
                    alias[a.asname or method] = top
                    bad = a.name not in exports and _unexported(method, a.name.split(".")[1:],
                                                                exports)  # fmt: skip
                    if bad or a.name not in exports and a.asname:
                        found.append(f"{name}:{node.lineno}: import {a.name}")
                continue
            for a in node.names:
                if f"{mod}.{a.name}" in exports:
                    alias[a.asname or a.name] = f"{mod}.{a.name}"
                elif mod not in exports or a.name not in exports[mod]:
                    found.append(f"{name}:{node.lineno}: from {mod} import {a.name}")
        for node in ast.walk(tree):
            chain = _dotted(node) if isinstance(node, ast.Attribute) else None
            if chain and chain[0] in alias and not isinstance(node.ctx, ast.Del):
                bad = _unexported(alias[chain[0]], chain[1:], exports)
                if bad:
                    found.append(f"{name}:{node.lineno}: {bad}")
    return sorted(set(found))


def harness_private_uses(modules, harness: str = "pylensfit_validation") -> list[str]:
    """Every private name (``_x``) of the harness's modules that a module of ``modules``
    imports or reads as an attribute of a harness module."""
    found = []
    for name, _, tree in modules:
        alias = {}
        for node, mod in _absolute_imports(tree):
            if mod.split(".")[0] != harness:
                continue
            for a in node.names:
                if isinstance(node, ast.Import):
                    alias[a.asname or a.name.split(".")[0]] = a.name
                elif a.name.startswith("_") and not a.name.startswith("__"):
                    found.append(f"{name}:{node.lineno}: from {mod} import {a.name}")
                else:
                    alias[a.asname or a.name] = f"{mod}.{a.name}"
        for node in ast.walk(tree):
            chain = _dotted(node) if isinstance(node, ast.Attribute) else None
            if chain and chain[0] in alias:
                private = [c for c in chain[1:] if c.startswith("_") and not c.startswith("__")]
                if private:
                    found.append(f"{name}:{node.lineno}: {'.'.join(chain)}")
    return sorted(set(found))


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycles(package):
    assert import_cycles(_package(PACKAGES[package])) == []


def test_no_layer_imports_a_higher_one():
    assert layer_violations(_package(SRC)) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_private_imports_across_modules(package):
    assert private_imports(_package(PACKAGES[package])) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_function_level_imports_say_why(package):
    assert silent_local_imports(_package(PACKAGES[package])) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_long_functions(package):
    limit = MAX_METHOD_LINES if package == "pylensfit" else MAX_LINES
    assert long_functions(_package(PACKAGES[package]), limit) == []


def test_numba_kernels_take_few_arguments():
    modules = _imported("pylensfit", SRC)
    assert any(isinstance(getattr(m, "py_func", None), types.FunctionType)
               for mod in modules for m in vars(mod).values())  # fmt: skip
    assert wide_kernels(modules) == []


def test_the_kernel_check_finds_a_wide_kernel():
    mod = types.ModuleType("m")
    exec("from numba import njit\n"
         "@njit\ndef wide(a, b, c, d, e, f, g, h, i, j, k):\n    return a\n"
         "@njit\ndef narrow(a, b, c, d, e, f, g, h, i, j):\n    return a\n"
         "def plain(a, b, c, d, e, f, g, h, i, j, k):\n    return a\n", mod.__dict__)  # fmt: skip
    assert wide_kernels([mod]) == ["m.wide: 11 arguments"]
    assert wide_kernels([mod], limit=9) == ["m.narrow: 10 arguments", "m.wide: 11 arguments"]


def test_the_method_imports_nothing_of_the_harness():
    assert harness_imports(_package(SRC)) == []


def test_the_harness_uses_only_what_the_method_exports():
    assert unexported_uses(_package(HARNESS), _exports()) == []


def test_the_benchmarks_use_only_what_the_method_exports():
    assert unexported_uses(_scripts(), _exports()) == []


def test_the_benchmarks_use_no_private_name_of_the_harness():
    assert harness_private_uses(_scripts()) == []


def test_the_benchmarks_compile():
    """Every benchmark and study compiles (the symbol table's errors too, such as a name
    used before its ``global`` declaration, which parsing alone does not see)."""
    bad = []
    for path in sorted(p for d in BENCHMARKS for p in d.glob("*.py")):
        try:
            compile(path.read_text(), str(path), "exec")
        except SyntaxError as err:
            bad.append(f"{path.name}: {err}")
    assert bad == []


def test_the_public_modules_are_documented():
    api = (ROOT / "docs" / "api.rst").read_text()
    assert [m for m in PUBLIC_MODULES[1:] if f".. automodule:: {m}\n" not in api] == []
    for m in PUBLIC_MODULES:
        mod = importlib.import_module(m)
        assert mod.__doc__, m
        assert [n for n in mod.__all__ if not hasattr(mod, n)] == [], m


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
    inner = [_module("p.__init__", "from .a import x\n"), _module("p.a", "from . import b\n"),
             _module("p.b", "def f():\n    from .a import y\n")]  # fmt: skip
    assert sorted(import_cycles(inner)) == [("p.a", "p.b"), ("p.b", "p.a")]
    layers = (("low",), ("p",), ("high",))
    stack = [_module("low", "from .p import x\n"), _module("p.__init__", "from ..high import y\n"),
             _module("high", "from . import low\n"), _module("stray", "")]  # fmt: skip
    assert layer_violations(stack, layers) == ["low -> p.__init__", "p.__init__ -> high",
                                                "stray: no layer"]  # fmt: skip


def test_the_layer_checks_find_what_they_are_for():
    method = [_module("m", "import os\ndef f():\n    from pylensfit_validation.cli import x\n"
                           "    import pylensfit_validation as v\n")]  # fmt: skip
    assert harness_imports(method) == [
        "m:3: from pylensfit_validation.cli import x", "m:4: import pylensfit_validation as v"]
    exports = {"pylensfit": {"Config", "measure"}, "pylensfit.shear": {"shapes"}}
    harness = [_module("h", "import pylensfit as plf\nimport pylensfit.shear\n"
                            "import pylensfit.grid\nimport pylensfit.prior as P\n"
                            "from pylensfit import Config, shear, pipeline\n"
                            "from pylensfit.shear import shapes, _all_sums\n"
                            "from pylensfit.likelihood import fit_stamps\n"
                            "plf.measure, plf.shear.shapes, plf.__version__, plf.pipeline\n"
                            "shear.kernel_columns, pylensfit.shear.sums_with, P.x\n")]  # fmt: skip
    assert unexported_uses(harness, exports) == [
        "h:3: import pylensfit.grid",
        "h:4: import pylensfit.prior",
        "h:5: from pylensfit import pipeline",
        "h:6: from pylensfit.shear import _all_sums",
        "h:7: from pylensfit.likelihood import fit_stamps",
        "h:8: pylensfit.pipeline",
        "h:9: pylensfit.prior.x",
        "h:9: pylensfit.shear.kernel_columns",
        "h:9: pylensfit.shear.sums_with",
    ]
    script = [_module("b", "import pylensfit_validation.precision as P\n"
                           "from pylensfit_validation import validation as V\n"
                           "from pylensfit_validation.stats import _hidden, shown\n"
                           "P._draw(V.read_truth, V._truth)\n")]  # fmt: skip
    assert harness_private_uses(script) == [
        "b:3: from pylensfit_validation.stats import _hidden",
        "b:4: P._draw",
        "b:4: V._truth",
    ]
