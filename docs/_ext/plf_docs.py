"""Sphinx extension of the pylensfit documentation: tables generated from the code.

Directives (each reads the package at build time, so that the pages never go stale):

``.. plf-config-table::``
    Every parameter of :class:`pylensfit.Config`, one table per section, from the
    declarative tables of :mod:`pylensfit.config.fields` (type, default, unit, allowed
    values or range, description).
``.. plf-presets::``
    The named configurations of :data:`pylensfit.config.PRESETS`.
``.. plf-hdus::``
    The catalogue's HDUs, :data:`pylensfit.catalogue.HDUS`.
``.. plf-columns::``
    The catalogue's columns, :data:`pylensfit.catalogue.COLUMNS`.
``.. plf-flags::``
    The flag bits, :data:`pylensfit.flags.FLAGS`.
``.. plf-cli-help:: [SUBCOMMAND]``
    The real ``pylensfit [SUBCOMMAND] --help`` output, as a literal block.

Descriptions and docstrings cite the method page's equations by their labels, as
"(docs: method, eq-key2)"; each ``eq-...`` label becomes a link to the equation (an
unknown label is an undefined reference, a warning). The build warns (an error under
``-W``) if a page speaks of the history of the package's making or of notes that are
not shipped, or if a name of ``pylensfit.__all__`` is left undocumented.
"""

from __future__ import annotations

import contextlib
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
# The method page's labels in the text that comes from the source tree
# ---------------------------------------------------------------------------------------
#: an equation label of docs/method.rst (``eq-key2``, ``eq-sensitivity-exact``)
_LABEL = re.compile(r"(?<![\w`<>/.-])eq-[a-z0-9]+(?:-[a-z0-9]+)*\b")
#: inline literals and roles, left as they are
_INLINE = re.compile(r"``.*?``|:\w+:`[^`]*`")


def _link_labels(text: str) -> str:
    """reST ``text`` with each bare ``eq-...`` label made a ``:ref:`` to it."""
    out, pos = [], 0
    for m in _INLINE.finditer(text):
        out.append(_LABEL.sub(lambda x: f":ref:`{x.group(0)} <{x.group(0)}>`",
                              text[pos:m.start()]))
        out.append(m.group(0))
        pos = m.end()
    out.append(_LABEL.sub(lambda x: f":ref:`{x.group(0)} <{x.group(0)}>`", text[pos:]))
    return "".join(out)


def _text_nodes(text: str) -> list[nodes.Node]:
    """Plain-text ``text`` (not parsed as reST) as nodes, its ``eq-...`` labels as links."""
    out: list[nodes.Node] = []
    pos = 0
    for m in _LABEL.finditer(text):
        out.append(nodes.Text(text[pos:m.start()]))
        ref = addnodes.pending_xref("", refdomain="std", reftype="ref",
                                    reftarget=m.group(0), refexplicit=True)
        ref += nodes.inline(m.group(0), m.group(0))
        out.append(ref)
        pos = m.end()
    out.append(nodes.Text(text[pos:]))
    return out


def _process_docstring(app, what, name, obj, options, lines):
    """autodoc: link the method page's labels of every docstring line."""
    lines[:] = [_link_labels(line) for line in lines]


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


def config_rows(section) -> list[list]:
    """The reference table's rows of one section of :data:`pylensfit.config.SECTIONS`:
    parameter, type, default, unit, allowed values or range, description."""
    return [[_lit(p.name), _lit(p.type_name), _lit(repr(p.default)), p.unit,
             _lit(p.allowed) if p.allowed else "", _text_nodes(p.doc)]
            for p in section.params]  # fmt: skip


class ConfigTable(Directive):
    """Every :class:`pylensfit.Config` parameter, one table per section, generated from
    the declarative tables of :mod:`pylensfit.config.fields`."""

    has_content = False

    def run(self):
        from pylensfit import config
        from pylensfit.config import SECTIONS, fields

        _depend(self, config, fields)
        out: list[nodes.Node] = []
        for section in SECTIONS:
            out.append(nodes.rubric("", "", nodes.Text(f"{section.title} "),
                                    nodes.literal(f"cfg.{section.name}",
                                                  f"cfg.{section.name}")))  # fmt: skip
            out.append(nodes.paragraph("", "", *_text_nodes(section.doc)))
            out.append(_table(["parameter", "type", "default", "unit", "allowed",
                               "description"], config_rows(section), [16, 8, 8, 8, 12, 48],
                              ids=[f"config-{p.name}" for p in section.params]))  # fmt: skip
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
            rows.append([_lit(name), _text_nodes(desc), _lit(over)])
        return [_table(["preset", "description", "overrides of Config()"], rows,
                       [10, 40, 50])]


class HdusTable(Directive):
    """The catalogue's HDUs, :data:`pylensfit.catalogue.HDUS`."""

    has_content = False

    def run(self):
        from pylensfit import catalogue
        from pylensfit.catalogue import HDUS

        _depend(self, catalogue)
        rows = [[_lit(name), _text_nodes(desc)] for name, desc in HDUS.items()]
        return [_table(["HDU", "contents"], rows, [12, 88],
                       ids=[f"hdu-{n.lower()}" for n in HDUS])]


class ColumnsTable(Directive):
    """The catalogue's columns, :data:`pylensfit.catalogue.COLUMNS`."""

    has_content = False

    def run(self):
        from pylensfit import catalogue
        from pylensfit.catalogue import COLUMNS

        _depend(self, catalogue)
        rows = [[_lit(name), unit, _text_nodes(desc)] for name, (unit, desc) in COLUMNS.items()]
        return [_table(["column", "unit", "meaning"], rows, [16, 6, 78],
                       ids=[f"column-{n.lower()}" for n in COLUMNS])]


class FlagsTable(Directive):
    """The flag bits, :data:`pylensfit.flags.FLAGS`."""

    has_content = False

    def run(self):
        from pylensfit import flags
        from pylensfit.flags import FLAGS

        _depend(self, flags)
        rows = [[str(bit), _lit(name), _text_nodes(desc)]
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
        from pylensfit import cli, config
        from pylensfit_validation import cli as harness_cli

        _depend(self, cli, config, harness_cli)
        env = self.state.document.settings.env
        env.plf_cli_docs = getattr(env, "plf_cli_docs", {})
        env.plf_cli_docs.setdefault(env.docname, set()).add(" ".join(self.arguments))
        argv = [*self.arguments, "--help"]
        text = cli_help(argv)
        if not text:
            return [self.state.document.reporter.warning(
                f"pylensfit {' '.join(argv)} printed nothing", line=self.lineno)]
        block = nodes.literal_block(text, text, language="text")
        return [block]


# ---------------------------------------------------------------------------------------
# Checks
# ---------------------------------------------------------------------------------------
# the words of a work diary, and the design note that is not shipped
_FORBIDDEN = re.compile(r"\bsess" r"ions?\b|DESIGN" r"\.md", re.I)


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
    """Warn if a built page speaks of the work's history or of the unshipped design note."""
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
    app.add_directive("plf-hdus", HdusTable)
    app.add_directive("plf-columns", ColumnsTable)
    app.add_directive("plf-flags", FlagsTable)
    app.add_directive("plf-cli-help", CliHelp)
    # numpydoc connects at priority 500: link the labels before it parses the docstring
    app.connect("autodoc-process-docstring", _process_docstring, priority=400)
    app.connect("env-check-consistency", _check_public_api)
    app.connect("env-check-consistency", _check_cli)
    app.connect("env-purge-doc", _purge_doc)
    app.connect("env-merge-info", _merge_info)
    app.connect("build-finished", _check_pages)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
