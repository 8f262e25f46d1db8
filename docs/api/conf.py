"""Sphinx configuration of the API reference (``sphinx-build -W -b html docs/api build/api``)."""

import mvintrinsic

project = "mvintrinsic"
author = "mvintrinsic developers"
copyright = "2026, mvintrinsic developers"
release = version = mvintrinsic.__version__

extensions = ["sphinx.ext.autodoc", "sphinx.ext.autosummary", "numpydoc", "sphinx.ext.mathjax"]
autosummary_generate = True
autodoc_default_options = {"members": True, "show-inheritance": False}
autodoc_typehints = "none"  # the numpydoc "Parameters" sections give types, shapes and units
numpydoc_show_class_members = False  # autosummary lists them
numpydoc_validation_checks: set[str] = set()
exclude_patterns = ["_build", "generated/*.tmp"]
html_theme = "alabaster"
