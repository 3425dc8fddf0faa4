"""Sphinx configuration: the user guide, the CLI reference (sphinx-click) and the API reference.

Build (what CI runs): ``python -m sphinx -b html -W --keep-going -q docs docs/_build/html``.
The benchmark pages are generated at build time from ``benchmarks/results/*.json`` by ``_ext/benchpages.py``.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "_ext"))

project = "terralod"
author = "terralod developers"
extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "sphinx_click",
    "benchpages",
]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
napoleon_numpy_docstring = True
napoleon_google_docstring = False
# numpy-style "Attributes" / "Parameters" entries name types in prose ("(N, 3) float64, metres"):
# they are documentation, not cross-references.
nitpicky = False
suppress_warnings = ["autodoc.import_object", "ref.python", "docutils"]
html_theme = "alabaster"
html_static_path = ["_static"]
html_theme_options = {"description": "terrain level of detail with measured error", "fixed_sidebar": True}
exclude_patterns = ["_build", "_ext"]
napoleon_use_ivar = True
