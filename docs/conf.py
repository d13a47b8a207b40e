"""Sphinx configuration of the pylensfit documentation.

Build: ``sphinx-build -W --keep-going -b html docs docs/_build/html`` (``.ci/docs``).
No network access is needed at build time: intersphinx is not used.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))
try:
    import pylensfit
except ImportError:  # building from a source tree without installing it
    sys.path.insert(0, str(HERE.parent / "src"))
    import pylensfit

project = "pylensfit"
author = "pylensfit developers"
copyright = "pylensfit developers"  # noqa: A001 (Sphinx's name)
release = pylensfit.__version__
version = ".".join(release.split(".")[:2])

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "plf_docs",
]

source_suffix = {".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build"]
templates_path: list[str] = []
default_role = "code"
smartquotes = False  # keep "--option" and quotes as written

# --- autodoc and numpydoc ---
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # the numpydoc sections carry the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_attributes_as_param_list = True

# --- math: MathJax is loaded by the reader's browser, nothing is fetched at build time ---
math_number_all = False

# --- myst (the changelog is Markdown) ---
myst_heading_anchors = 3

# --- HTML ---
html_theme = "alabaster"
html_title = f"pylensfit {release}"
html_static_path: list[str] = []
html_copy_source = False
html_show_sourcelink = False
html_theme_options = {
    "description": "Bayesian galaxy shapes and weak-lensing shear (lensfit)",
    "fixed_sidebar": True,
    "page_width": "1180px",
    "sidebar_width": "240px",
}
html_sidebars = {"**": ["about.html", "navigation.html", "searchbox.html"]}
