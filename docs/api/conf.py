"""Sphinx configuration of the API reference (``make docs``): body_scheme_core from its numpydoc docstrings."""

project = "body_scheme_core"
author = "Body Scheme developers"
extensions = ["sphinx.ext.autodoc", "numpydoc", "sphinx.ext.mathjax"]
autodoc_default_options = {"members": True, "show-inheritance": True, "ignore-module-all": True}
autodoc_member_order = "bysource"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
html_theme = "alabaster"
exclude_patterns = []
numpydoc_attributes_as_param_list = True
autodoc_typehints = "none"  # the docstrings give the types (numpydoc); annotations would be cross-referenced twice
