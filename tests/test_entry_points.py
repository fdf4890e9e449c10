"""Every ``ros2 run`` executable of the packages names a module of its own package with a ``main``, once."""

from __future__ import annotations

import ast
import importlib
import pathlib

SRC = pathlib.Path(__file__).resolve().parents[1] / "ros2_ws" / "src"


def _console_scripts():
    """``[(package, executable, "module:function")]`` from each package's setup.py."""
    found = []
    for setup in sorted(SRC.glob("*/setup.py")):
        for node in ast.walk(ast.parse(setup.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Dict):
                for key, value in zip(node.keys, node.values, strict=True):
                    if isinstance(key, ast.Constant) and key.value == "console_scripts":
                        for item in value.elts:
                            name, target = (part.strip() for part in item.value.split("="))
                            found.append((setup.parent.name, name, target))
    return found


def test_every_executable_runs_a_main_of_its_own_package():
    scripts = _console_scripts()
    assert len(scripts) >= 10
    for package, name, target in scripts:
        module, function = target.split(":")
        assert module.split(".")[0] == package, f"{package}'s {name} runs {module}, another package's module"
        assert callable(getattr(importlib.import_module(module), function)), target
    names = [(package, name) for package, name, _ in scripts]
    assert len(names) == len(set(names))
