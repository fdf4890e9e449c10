"""``print_markers``: the sheet to print for a marker file (one you wrote, or edited after ``plan_markers``).

    python -m body_scheme_apps.print_markers markers/markers.yaml [--dpi 300] [--out markers/markers]

Writes ``<out>.pdf`` (A4 pages at true scale: print at "actual size", not "fit to page"; check a square with a
ruler) and ``<out>.png`` (``<out>-<page>.png`` for several pages); ``<out>`` is the marker file's path without its
suffix by default. The tags of a flat plate (one ``plate`` key, in one plane) are printed as one piece at their
places on the plate (:mod:`body_scheme_sim.sheet`).
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.world import load_markers_yaml

from .entry import command

__all__ = ["main"]


@command
def main(argv=None):
    """Console entry point; exit code 1 with a one-line error."""
    from body_scheme_sim.sheet import write_sheet

    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.print_markers",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("markers", help="the marker file (YAML: id, link, xyz, rpy, size, plate)")
    parser.add_argument("--dpi", type=int, default=300, help="resolution of the sheet (default: %(default)s)")
    parser.add_argument("--out", help="the sheet's path without suffix (default: the marker file's)")
    args = parser.parse_args(argv)
    stem = pathlib.Path(args.out) if args.out else pathlib.Path(args.markers).with_suffix("")
    try:
        markers = load_markers_yaml(pathlib.Path(args.markers))
        if not markers:
            raise BodySchemeError(f"{args.markers} lists no marker")
        stem.parent.mkdir(parents=True, exist_ok=True)
        sheet = write_sheet(markers, stem, dpi=args.dpi)
    except (OSError, BodySchemeError) as error:
        print(f"print_markers: {error}", file=sys.stderr)
        return 1
    print(f"wrote {', '.join(str(path) for path in sheet)}: print at actual size")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
