"""Point the ROS wheels' exported CMake files at this venv's Python and numpy include directories.

The ROS 2 Jazzy wheels on PyPI were built in a manylinux container and their exported CMake files hard-code
``/opt/python/cp311-cp311/...`` include paths; CMake refuses to generate when those do not exist. This rewrites them
to the real paths of the running interpreter (no root needed). Idempotent: a second run changes nothing.

Usage: ``.venv/bin/python tools/fix_cmake_paths.py`` (``make`` runs it after installing the wheels).
"""

from __future__ import annotations

import pathlib
import sys
import sysconfig

import numpy

BUILD_PREFIX = "/opt/python/cp311-cp311"
REPLACEMENTS = {
    f"{BUILD_PREFIX}/lib/python3.11/site-packages/numpy/_core/include": numpy.get_include(),
    f"{BUILD_PREFIX}/include/python3.11": sysconfig.get_paths()["include"],
}


def main() -> int:
    share = pathlib.Path(sys.prefix) / "share"
    changed = 0
    for path in share.rglob("*.cmake"):
        text = path.read_text()
        if BUILD_PREFIX not in text:
            continue
        for old, new in REPLACEMENTS.items():
            text = text.replace(old, new)
        path.write_text(text)
        changed += 1
    left = [p for p in share.rglob("*.cmake") if BUILD_PREFIX in p.read_text()]
    if left:
        print(f"fix_cmake_paths: {len(left)} file(s) still reference {BUILD_PREFIX}, e.g. {left[0]}", file=sys.stderr)
        return 1
    print(f"fix_cmake_paths: rewrote {changed} CMake file(s) under {share}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
