"""Sphinx configuration: the API reference generated from terralod's numpy-style docstrings.

Build (what CI runs): ``python -m sphinx -b html -W --keep-going -q docs docs/_build/html``.
"""

project = "terralod"
author = "terralod developers"
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.viewcode"]
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
exclude_patterns = ["_build"]
napoleon_use_ivar = True
