"""Regenerate or check the shipped robot files: ``python -m body_scheme_sim.robots --write | --check``."""

from __future__ import annotations

import argparse
import pathlib
import sys

from . import MARKERS_SUFFIX, ROBOT_BUILDERS, ROBOTS_DIR, generate_robot_files, write_robot_files


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m body_scheme_sim.robots", description=__doc__)
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--write", action="store_true", help="(re)write the URDF and marker files")
    action.add_argument("--check", action="store_true", help="exit 1 if a shipped file differs from a fresh one")
    parser.add_argument("--dir", default=str(ROBOTS_DIR), help=f"target directory (default {ROBOTS_DIR})")
    args = parser.parse_args(argv)
    if args.write:
        for path in write_robot_files(args.dir):
            print(f"wrote {path}")
        return 0
    stale = []
    for name in ROBOT_BUILDERS:
        for suffix, text in zip((".urdf", MARKERS_SUFFIX), generate_robot_files(name), strict=True):
            path = pathlib.Path(args.dir) / f"{name}{suffix}"
            if not path.is_file() or path.read_text(encoding="utf-8") != text:
                stale.append(str(path))
    for path in stale:
        print(f"stale: {path}")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
