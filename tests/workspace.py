"""What the workspace's packages and docs declare, read from their sources (shared by the cross-package tests)."""

from __future__ import annotations

import ast
import pathlib
import re
import shlex

import pybullet_data

REPO = pathlib.Path(__file__).resolve().parents[1]
SRC = REPO / "ros2_ws" / "src"


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


DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
#: What each ``$(...)`` in the docs gives in a shell (a new one is named by the test, to be added here).
SUBSTITUTIONS = {
    '$(python -c "import pybullet_data; print(pybullet_data.getDataPath())")': pybullet_data.getDataPath(),
}


def documented_commands():
    """``[(doc name, command words)]``: each command of each ``bash`` block (continuations joined, ``&&`` split,
    comments dropped, ``$(...)`` substituted). A synopsis (``BAG [--params FILE]``, ``pause | resume``) is not one."""
    found = []
    for doc in DOCS:
        for block in re.findall(r"^```bash\n(.*?)^```", doc.read_text(encoding="utf-8"), re.S | re.M):
            for line in block.replace("\\\n", " ").splitlines():
                for text, value in SUBSTITUTIONS.items():
                    line = line.replace(text, value)
                assert "$(" not in line, f"{doc.name}: add what {line!r}'s substitution gives to SUBSTITUTIONS"
                for command in line.split("&&"):
                    words = shlex.split(command, comments=True)
                    if words and not any(word.startswith("[") or word == "|" for word in words):
                        found.append((doc.name, words))
    return found
