"""What the workspace's packages declare, read from their sources (shared by the cross-package tests)."""

from __future__ import annotations

import ast
import pathlib

SRC = pathlib.Path(__file__).resolve().parents[1] / "ros2_ws" / "src"


def console_scripts():
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
