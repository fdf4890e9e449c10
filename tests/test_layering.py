"""The packages import only downwards (docs/architecture.md): core <- sim <- nodes <- apps, and msgs below the nodes.

Every module and every test file of each package is parsed (not imported) and its imports of our packages are
checked against the package's allowed dependencies, so neither a library nor a test closes a cycle.
"""

from __future__ import annotations

import ast
import importlib
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


# ---------------------------------------------------------------------------------------------- inside the core
CORE = SRC / "body_scheme_core" / "body_scheme_core"
#: The core's units (a top-level module or a subpackage) by layer: a unit imports only units of lower layers, so the
#: paper's concepts stack as docs/architecture.md draws them.
CORE_LAYERS = {
    "errors": 0, "limits": 0, "rotations": 0,  # named exceptions, the sizes every input check shares, rotation maths
    "threads": 1,  # one math-library thread per process
    "transforms": 1, "state_values": 1, "events": 1,  # rigid-transform maths, saved-value readers, the learner's events
    "levenberg_marquardt": 1,  # the one damped Gauss-Newton step of every nonlinear fit
    "models": 2, "perception": 2, "pairing": 2,  # local models (Sec. III-A/B); the camera and the commands
    "world": 3,  # kinematic trees, robots, faults and sessions: the bodies we learn
    "plates": 3,  # several tags on one rigid plate: one pose (perception)
    "prediction": 4,  # the body scheme and its predictions (Sec. III-C/D, Eq. 8)
    "calibration": 5, "control": 5,  # the joint fit; IK and exploration (Sec. III-D)
    "learning": 6,  # structure search, learning and adaptation (Sec. III-A-C, III-E)
}
SUBPACKAGES = sorted(unit for unit in CORE_LAYERS if (CORE / unit).is_dir())


def core_imports(path):
    """``[(unit, module path inside the core, names)]`` of every import of the core in a file (see
    :func:`imports_of`)."""
    package = None
    if path.is_relative_to(CORE.parent):
        package = path.relative_to(CORE.parent).parts[:-1]
    return imports_of(path.read_text(encoding="utf-8"), package)


def imports_of(source, package):
    """``[(unit, module path inside the core, names)]`` of every import of the core in ``source``, relative imports
    resolved from ``package`` (a core package's dotted parts, or None outside the core); module paths like
    ``learning.pool``, names None for ``import x``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                if package is None:
                    continue  # a relative import in another package stays in that package
                target = list(package[:len(package) - node.level + 1]) + (node.module.split(".") if node.module else [])
            else:
                target = (node.module or "").split(".")
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                target = alias.name.split(".")
                if target[0] == "body_scheme_core" and len(target) > 1:
                    found.append((target[1], ".".join(target[1:]), None))
            continue
        else:
            continue
        if target[0] != "body_scheme_core":
            continue
        if len(target) == 1:  # from body_scheme_core import x / from .. import x
            found.extend((name, name, None) for name in names if name in CORE_LAYERS)
        else:
            found.append((target[1], ".".join(target[1:]), names))
    return found


def unit_of(path):
    """The core unit a core file belongs to."""
    return path.relative_to(CORE).with_suffix("").parts[0]


def test_every_core_module_belongs_to_a_layer():
    units = {unit_of(path) for path in CORE.rglob("*.py") if path.name != "__init__.py" or path.parent != CORE}
    assert units == set(CORE_LAYERS)


def test_core_units_import_only_lower_layers():
    wrong = []
    for path in sorted(CORE.rglob("*.py")):
        if path.parent == CORE and path.name == "__init__.py":
            continue
        mine = unit_of(path)
        for unit, module, _ in core_imports(path):
            if unit not in CORE_LAYERS:
                wrong.append(f"{path.relative_to(CORE)} imports {module}, a unit of no layer (add it to CORE_LAYERS)")
            elif unit != mine and CORE_LAYERS[unit] >= CORE_LAYERS[mine]:
                wrong.append(f"{path.relative_to(CORE)} imports {module} (layer {CORE_LAYERS[unit]} >= "
                             f"{CORE_LAYERS[mine]})")
    assert wrong == []


def private_attributes(source, public):
    """``[dotted name]`` of attribute accesses past a subpackage's public names in ``source``: ``learning.pool`` after
    ``from body_scheme_core import learning`` (or ``from .. import learning``), ``body_scheme_core.learning.pool``
    after ``import body_scheme_core.learning``. ``public``: ``{subpackage: its __all__}``."""
    tree = ast.parse(source)
    bound = {}  # local name -> subpackage
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module in (None, "body_scheme_core")):
            bound.update({alias.asname or alias.name: alias.name for alias in node.names if alias.name in public})
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        chain, value = [node.attr], node.value
        while isinstance(value, ast.Attribute):
            chain.append(value.attr)
            value = value.value
        if not isinstance(value, ast.Name):
            continue
        chain = [value.id] + chain[::-1]
        if chain[0] == "body_scheme_core" and len(chain) > 2 and chain[1] in public:
            sub, name = chain[1], chain[2]
        elif chain[0] in bound and len(chain) > 1:
            sub, name = bound[chain[0]], chain[1]
        else:
            continue
        if name not in public[sub]:
            found.append(".".join(chain))
    return found


def _library_files():
    """Every library module of our Python packages (tests excluded: a test may import the module it tests)."""
    for package in ALLOWED:
        yield from sorted((SRC / package / package).rglob("*.py"))


def test_subpackages_are_imported_only_through_their_public_names():
    """Outside a subpackage of the core (in the core or in another package), its modules are not imported, nor
    reached as attributes: only the names its ``__init__`` exports."""
    public = {unit: set(importlib.import_module(f"body_scheme_core.{unit}").__all__) for unit in SUBPACKAGES}
    wrong = []
    for path in _library_files():
        mine = unit_of(path) if path.is_relative_to(CORE) else None
        for unit, module, names in core_imports(path):
            if unit in SUBPACKAGES and unit != mine:
                if module != unit or not set(names or ()) <= public[unit]:
                    wrong.append(f"{path.relative_to(SRC)}: {module} {names}")
        others = {unit: names for unit, names in public.items() if unit != mine}
        wrong += [f"{path.relative_to(SRC)}: {name}"
                  for name in private_attributes(path.read_text(encoding="utf-8"), others)]
    assert wrong == []


def test_the_public_names_checker_sees_attribute_access():
    public = {"learning": {"BodySchemeLearner"}}
    source = ("from .. import learning\nimport body_scheme_core.learning\nlearning.pool.Targets\n"
              "body_scheme_core.learning.tracked\nlearning.BodySchemeLearner\n")
    assert sorted(private_attributes(source, public)) == ["body_scheme_core.learning.tracked", "learning.pool",
                                                          "learning.pool.Targets"]


def test_the_layer_checker_resolves_relative_imports():
    """``from ..learning.pool import x`` in a module of control/ is an import of learning (a higher layer); a relative
    import in another package is that package's own."""
    source = "from ..learning.pool import Targets\nfrom .ik import solve_ik\nfrom ..errors import X\n"
    assert imports_of(source, ("body_scheme_core", "control")) == [("learning", "learning.pool", ["Targets"]),
                                                                  ("control", "control.ik", ["solve_ik"]),
                                                                  ("errors", "errors", ["X"])]
    assert imports_of(source, None) == []


MAX_MODULE_LINES = 500


def test_no_library_module_grows_past_500_lines():
    """Every library module (not tests) is at most 500 lines (issue 35): a module that grows past it is split by
    concept, as transforms / rotations, the scheme / its Jacobian, the world / its scene and collision screen were."""
    lengths = {str(path.relative_to(SRC)): len(path.read_text(encoding="utf-8").splitlines())
               for package in OURS for path in (SRC / package / package).rglob("*.py")}
    assert len(lengths) > 100  # the walk found the packages
    assert {name: n for name, n in lengths.items() if n > MAX_MODULE_LINES} == {}
