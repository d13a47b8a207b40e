"""Sphinx extension of the pylensfit documentation: tables generated from the code.

Directives (each reads the package at build time, so that the pages never go stale):

``.. plf-config-table::``
    Every field of :class:`pylensfit.Config` (``dataclasses.fields``) with its type,
    default and the description stored in the field's metadata (``metadata["doc"]``),
    grouped under the ``# --- group ---`` comments of the class body.
``.. plf-presets::``
    The named configurations of :data:`pylensfit.config.PRESETS`.
``.. plf-columns::``
    The catalogue's columns, :data:`pylensfit.catalogue.COLUMNS`.
``.. plf-flags::``
    The flag bits, :data:`pylensfit.flags.FLAGS`.
``.. plf-cli-help:: [SUBCOMMAND]``
    The real ``pylensfit [SUBCOMMAND] --help`` output, as a literal block.

Descriptions and docstrings written for the source tree may point at notes that are
not part of the documentation, or date a measurement; :func:`clean_text` rewrites
those references before they reach a page, and the build warns (an error under ``-W``)
if a page still holds one, or if a name of ``pylensfit.__all__`` is left undocumented.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import io
import os
import re
from pathlib import Path

from docutils import nodes
from docutils.parsers.rst import Directive, directives
from sphinx import addnodes
from sphinx.util import logging

logger = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------
# Cleaning the text that comes from the source tree
# ---------------------------------------------------------------------------------------
_UNITS = ("first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|"
          "twelfth|thirteenth|fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|"
          "nineteenth")
_TENS = "twentieth|thirtieth|fortieth|fiftieth|sixtieth|seventieth|eightieth|ninetieth"
_DECADES = "twenty|thirty|forty|fifty|sixty|seventy|eighty|ninety"
_ORD = rf"(?:(?:{_DECADES})-(?:{_UNITS})|{_TENS}|{_UNITS})"
_ORDS = rf"(?:the\s+)?{_ORD}(?:(?:,\s*|,?\s+and\s+){_ORD})*\s+sessions?"
#: "(..., thirtieth session)" -> "(...)"; "(thirty-sixth session)" -> ""
_SESSION_PATTERNS = [
    (re.compile(rf"\s*\(\s*{_ORDS}\s*\)", re.I), ""),
    (re.compile(rf"\s*[,;]\s*{_ORDS}\b", re.I), ""),
    (re.compile(rf"\b{_ORDS}\s*[,;]\s*", re.I), ""),
    (re.compile(rf"\s*\b{_ORDS}\b", re.I), ""),
]
#: the notes' sections -> the method page's labels
_NOTE_SECTIONS = {"1": "conventions", "2": "likelihood", "3": "likelihood",
                  "2-3": "likelihood", "4": "eq-sensitivity-exact"}
_NOTE_TITLES = {"conventions": "the conventions", "likelihood": "the likelihood",
                "eq-sensitivity-exact": "the exact shear sensitivity",
                "bayes": "the prior, the posterior and the shear"}
_NOTE = re.compile(
    r"`{0,2}(?:\.\./)?(?:shared/)?DESIGN\.md`{0,2}(?P<own>'s)?"
    r"(?:,?\s*(?:s\.\s*|sections?\s+)(?P<sec>\d(?:\s*-\s*\d|\s+and\s+\d)?))?"
)


def _note_target(sec: str | None) -> str:
    if not sec:
        return "method"
    key = re.sub(r"\s+", "", sec).replace("and", "-")
    return _NOTE_SECTIONS.get(key, _NOTE_SECTIONS.get(key[:1], "method"))


def clean_text(text: str, *, rst: bool = True) -> str:
    """``text`` with the source tree's references to its notes and their dates rewritten.

    A reference to the design notes becomes one to the method page (a ``:ref:`` role
    when ``rst``, plain words otherwise); a measurement dated by a working period keeps
    its numbers and its file, without the date.
    """
    def note(m: re.Match) -> str:
        target = _note_target(m.group("sec"))
        before = text[max(0, m.start() - 80):m.start()]
        if target == "eq-sensitivity-exact" and "sensitiv" not in before:
            target = "bayes"  # section 4 is the prior, the posterior and the shear as well
        if target == "method":
            return ":doc:`the method page </method>`" if rst else "the method page"
        title = _NOTE_TITLES[target]
        return f":ref:`{title} <{target}>`" if rst else f"{title} (method page)"

    text = _NOTE.sub(note, text)
    for pat, rep in _SESSION_PATTERNS:
        text = pat.sub(rep, text)
    return text


def _note_nodes(text: str) -> list[nodes.Node]:
    """Plain-text ``text`` (not parsed as reST) as nodes, its note references as links."""
    out: list[nodes.Node] = []
    pos = 0
    text = clean_text(text, rst=False)
    titles = {t: label for label, t in _NOTE_TITLES.items()}
    alts = "|".join(re.escape(t) for t in titles)
    for m in re.finditer(rf"({alts}) \(method page\)|the method page", text):
        out.append(nodes.Text(text[pos:m.start()]))
        if m.group(1):
            label = titles[m.group(1)]
            ref = addnodes.pending_xref("", refdomain="std", reftype="ref",
                                        reftarget=label, refexplicit=True)
            ref += nodes.inline(m.group(1), m.group(1))
        else:
            ref = addnodes.pending_xref("", refdomain="std", reftype="doc",
                                        reftarget="/method", refexplicit=True)
            ref += nodes.inline("the method page", "the method page")
        out.append(ref)
        pos = m.end()
    out.append(nodes.Text(text[pos:]))
    return out


def _process_docstring(app, what, name, obj, options, lines):
    """autodoc: clean every docstring line by line (whole text, to catch wrapped phrases)."""
    if not lines:
        return
    cleaned = clean_text("\n".join(lines)).split("\n")
    lines[:] = cleaned


# ---------------------------------------------------------------------------------------
# Table helpers
# ---------------------------------------------------------------------------------------
def _table(header: list[str], rows: list[list[list[nodes.Node] | str]], widths: list[int],
           ids: list[str] | None = None) -> nodes.table:
    table = nodes.table(classes=["plf-table", "colwidths-given"])
    tgroup = nodes.tgroup(cols=len(header))
    table += tgroup
    for w in widths:
        tgroup += nodes.colspec(colwidth=w)
    thead = nodes.thead()
    tgroup += thead
    row = nodes.row()
    for h in header:
        row += nodes.entry("", nodes.paragraph(text=h))
    thead += row
    tbody = nodes.tbody()
    tgroup += tbody
    for i, cells in enumerate(rows):
        row = nodes.row()
        if ids is not None:
            row["ids"] = [ids[i]]
        for cell in cells:
            para = nodes.paragraph()
            if isinstance(cell, str):
                para += nodes.Text(cell)
            else:
                para.extend(cell)
            row += nodes.entry("", para)
        tbody += row
    return table


def _depend(directive: Directive, *modules) -> None:
    """Read the page again when one of ``modules``' source files changes."""
    env = directive.state.document.settings.env
    for mod in modules:
        path = inspect.getsourcefile(mod)
        if path:
            env.note_dependency(path)


def _lit(text: str) -> list[nodes.Node]:
    return [nodes.literal(text, text)]


def _config_groups(cls) -> list[tuple[str, list[str]]]:
    """``[(group title, [field names])]`` from the ``# --- title ---`` comments of ``cls``."""
    names = [f.name for f in dataclasses.fields(cls)]
    try:
        src = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return [("", names)]
    groups: list[tuple[str, list[str]]] = [("", [])]
    header = re.compile(r"^\s*#\s*-{2,}\s*(.*?)\s*-{2,}\s*$")
    field_line = re.compile(r"^    (\w+)\s*:")
    known = set(names)
    for line in src:
        h = header.match(line)
        if h:
            groups.append((h.group(1), []))
            continue
        f = field_line.match(line)
        if f and f.group(1) in known:
            groups[-1][1].append(f.group(1))
    seen = {n for _, g in groups for n in g}
    missing = [n for n in names if n not in seen]
    if missing:  # anything the source scan missed still gets a row
        groups.append(("other settings", missing))
    return [(t, g) for t, g in groups if g]


class ConfigTable(Directive):
    """Every :class:`pylensfit.Config` field: type, default, description."""

    has_content = False

    def run(self):
        from pylensfit import Config, config

        _depend(self, config)
        fields = {f.name: f for f in dataclasses.fields(Config)}
        out: list[nodes.Node] = []
        for title, names in _config_groups(Config):
            if title:
                rubric = nodes.rubric(text=clean_text(title, rst=False)[:1].upper()
                                      + clean_text(title, rst=False)[1:])
                out.append(rubric)
            rows = []
            for name in names:
                f = fields[name]
                typ = f.type if isinstance(f.type, str) else getattr(f.type, "__name__",
                                                                      str(f.type))
                rows.append([_lit(name), _lit(typ), _lit(repr(f.default)),
                             _note_nodes(f.metadata.get("doc", ""))])
            out.append(_table(["field", "type", "default", "description"], rows,
                              [18, 6, 10, 66], ids=[f"config-{n}" for n in names]))
        return out


class PresetsTable(Directive):
    """The named configurations of :data:`pylensfit.config.PRESETS`."""

    has_content = False

    def run(self):
        from pylensfit import config
        from pylensfit.config import PRESETS

        _depend(self, config)
        rows = []
        for name, (overrides, desc) in PRESETS.items():
            over = ", ".join(f"{k}={v!r}" for k, v in overrides.items()) or "(none)"
            rows.append([_lit(name), _note_nodes(desc), _lit(over)])
        return [_table(["preset", "description", "overrides of Config()"], rows,
                       [10, 40, 50])]


class ColumnsTable(Directive):
    """The catalogue's columns, :data:`pylensfit.catalogue.COLUMNS`."""

    has_content = False

    def run(self):
        from pylensfit import catalogue
        from pylensfit.catalogue import COLUMNS

        _depend(self, catalogue)
        rows = [[_lit(name), unit, _note_nodes(desc)] for name, (unit, desc) in COLUMNS.items()]
        return [_table(["column", "unit", "meaning"], rows, [16, 6, 78],
                       ids=[f"column-{n.lower()}" for n in COLUMNS])]


class FlagsTable(Directive):
    """The flag bits, :data:`pylensfit.flags.FLAGS`."""

    has_content = False

    def run(self):
        from pylensfit import flags
        from pylensfit.flags import FLAGS

        _depend(self, flags)
        rows = [[str(bit), _lit(name), _note_nodes(desc)]
                for name, (bit, desc) in FLAGS.items()]
        return [_table(["bit", "name", "meaning"], rows, [8, 16, 76])]


def cli_help(argv: list[str], columns: int = 92) -> str:
    """What ``pylensfit ARGV`` prints (``--help``), at a fixed width."""
    from pylensfit.cli import main

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(columns)
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
            try:
                main(argv)
            except SystemExit:
                pass
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old
    return buf.getvalue().rstrip()


class CliHelp(Directive):
    """``.. plf-cli-help:: measure``: the subcommand's ``--help`` as a literal block."""

    has_content = False
    optional_arguments = 1
    option_spec = {"caption": directives.unchanged}

    def run(self):
        from pylensfit import cli, config, validation

        _depend(self, cli, config, validation)
        env = self.state.document.settings.env
        env.plf_cli_docs = getattr(env, "plf_cli_docs", {})
        env.plf_cli_docs.setdefault(env.docname, set()).add(" ".join(self.arguments))
        argv = [*self.arguments, "--help"]
        text = cli_help(argv)
        if not text:
            return [self.state.document.reporter.warning(
                f"pylensfit {' '.join(argv)} printed nothing", line=self.lineno)]
        text = clean_text(text, rst=False)
        block = nodes.literal_block(text, text, language="text")
        return [block]


# ---------------------------------------------------------------------------------------
# Checks
# ---------------------------------------------------------------------------------------
_FORBIDDEN = re.compile(r"\bsessions?\b|DESIGN\.md", re.I)


def _check_public_api(app, env):
    """Warn for each name of ``pylensfit.__all__`` that no page documents."""
    import pylensfit

    objects = env.get_domain("py").objects
    for name in pylensfit.__all__:
        if f"pylensfit.{name}" not in objects:
            logger.warning("pylensfit.%s (in pylensfit.__all__) is not documented: add it "
                           "to docs/api.rst", name, type="plf", subtype="api")


def _subcommands() -> list[str]:
    import argparse

    from pylensfit.cli import build_parser

    for action in build_parser()._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    return []


def _check_cli(app, env):
    """Warn for each ``pylensfit`` subcommand whose help no page shows."""
    shown = set().union(*getattr(env, "plf_cli_docs", {}).values())
    for cmd in _subcommands():
        if cmd not in shown:
            logger.warning("the subcommand 'pylensfit %s' has no '.. plf-cli-help:: %s' "
                           "in docs/cli.rst", cmd, cmd, type="plf", subtype="cli")


def _purge_doc(app, env, docname):
    getattr(env, "plf_cli_docs", {}).pop(docname, None)


def _merge_info(app, env, docnames, other):
    env.plf_cli_docs = getattr(env, "plf_cli_docs", {})
    env.plf_cli_docs.update(getattr(other, "plf_cli_docs", {}))


def _check_pages(app, exception):
    """Warn if a built page still refers to the source tree's notes or dates its numbers."""
    if exception is not None or app.builder.format != "html":
        return
    outdir = Path(app.outdir)
    for page in sorted(outdir.rglob("*.html")):
        text = page.read_text(encoding="utf-8", errors="replace")
        text = re.sub(r"<script.*?</script>|<[^>]+>", " ", text, flags=re.S)
        for m in _FORBIDDEN.finditer(text):
            ctx = " ".join(text[max(0, m.start() - 60):m.end() + 60].split())
            logger.warning("%s: the page says %r (... %s ...)", page.relative_to(outdir),
                           m.group(0), ctx, type="plf", subtype="words")


def setup(app):
    app.add_directive("plf-config-table", ConfigTable)
    app.add_directive("plf-presets", PresetsTable)
    app.add_directive("plf-columns", ColumnsTable)
    app.add_directive("plf-flags", FlagsTable)
    app.add_directive("plf-cli-help", CliHelp)
    # numpydoc connects at priority 500: clean the raw docstring before it parses it
    app.connect("autodoc-process-docstring", _process_docstring, priority=400)
    app.connect("env-check-consistency", _check_public_api)
    app.connect("env-check-consistency", _check_cli)
    app.connect("env-purge-doc", _purge_doc)
    app.connect("env-merge-info", _merge_info)
    app.connect("build-finished", _check_pages)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
