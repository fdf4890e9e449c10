"""The packages import only downwards (docs/architecture.md): core <- sim <- nodes <- apps, and msgs below the nodes.

Every module and every test file of each package is parsed (not imported) and its imports of our packages are
checked against the package's allowed dependencies, so neither a library nor a test closes a cycle.
"""

from __future__ import annotations

import ast
import pathlib
import xml.etree.ElementTree as ET

import pytest

SRC = pathlib.Path(__file__).resolve().parents[1] / "ros2_ws" / "src"
OURS = ("body_scheme_core", "body_scheme_sim", "body_scheme_nodes", "body_scheme_msgs", "body_scheme_apps")
#: Package -> the packages of ours it may import (besides itself).
ALLOWED = {
    "body_scheme_core": set(),
    "body_scheme_sim": {"body_scheme_core"},
    "body_scheme_nodes": {"body_scheme_core", "body_scheme_sim", "body_scheme_msgs"},
    "body_scheme_apps": {"body_scheme_core", "body_scheme_sim", "body_scheme_nodes", "body_scheme_msgs"},
}


def imported_packages(path):
    """Our top-level packages imported anywhere in a Python file (module level or inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        found.update(name.split(".")[0] for name in names if name.split(".")[0] in OURS)
    return found


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_only_downwards(package):
    files = sorted((SRC / package).rglob("*.py"))
    assert files
    wrong = {str(path.relative_to(SRC)): sorted(imported_packages(path) - ALLOWED[package] - {package})
             for path in files}
    assert {path: names for path, names in wrong.items() if names} == {}


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_xml_declares_the_packages_it_imports(package):
    """Each of our packages that a package imports is an exec_depend (or depend) of its package.xml."""
    root = ET.parse(SRC / package / "package.xml").getroot()
    declared = {element.text for element in root if element.tag in ("depend", "exec_depend")}
    imported = set().union(*(imported_packages(path) for path in (SRC / package / package).rglob("*.py")))
    assert imported - {package} <= declared


def test_the_checker_sees_imports_inside_functions(tmp_path):
    """A lazy import in a function body counts like a module-level one (the check cannot be dodged)."""
    path = tmp_path / "lazy.py"
    path.write_text("def f():\n    from body_scheme_apps.experiments import runner\n    import body_scheme_sim.world\n")
    assert imported_packages(path) == {"body_scheme_apps", "body_scheme_sim"}
