"""``plan_markers``: where to put the markers on your robot, and a sheet to print them on.

    python -m body_scheme_apps.plan_markers --robot path/to/robot.urdf [--camera auto | "x y z r p y"]
        [--links link1,link2] [--package-path DIR] [--dpi 300] --out DIR

Writes to ``DIR``: ``markers.yaml`` (the placement file every command and node reads), ``markers.pdf`` (A4 pages at
true scale: print at "actual size", not "fit to page"; check a square with a ruler) and ``markers.png``, and
``camera.yaml`` (the camera pose the plan assumes, as sim_node parameters), and ``scheme_node.yaml`` (scheme_node's
parameter file for this robot: its part ids, joints, limits and a tracker's noise priors). The plan is
:func:`body_scheme_sim.planning.plan_markers`: one marker per moving body, on its surface, facing the camera over the
joint range, seen together with the marker above it as often as possible.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from body_scheme_core.errors import BodySchemeError

from .entry import command
from .robot_option import scheme_parameters_path, write_scheme_parameters

__all__ = ["main"]


@command
def main(argv=None):
    """Console entry point; exit code 1 with a one-line error."""
    from body_scheme_sim.camera import write_camera
    from body_scheme_sim.markers import beside_markers
    from body_scheme_sim.planning import parse_camera, plan_markers, write_markers
    from body_scheme_sim.sheet import write_sheet

    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.plan_markers",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--robot", required=True, help="the robot's URDF path (or a shipped robot's name)")
    parser.add_argument("--camera", default="auto",
                        help='"x y z roll pitch yaw" of the camera\'s optical frame in the world (m, rad), or auto '
                             "(default: framing the arm)")
    parser.add_argument("--links", help="comma-separated links to put markers on (default: every moving body and the "
                                        "root)")
    parser.add_argument("--package-path", action="append", default=[], metavar="DIR",
                        help="a directory searched first for package:// meshes (repeatable)")
    parser.add_argument("--dpi", type=int, default=300, help="resolution of the sheet (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output directory")
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        links = args.links.split(",") if args.links else None
        planned, skipped, camera = plan_markers(args.robot, camera=parse_camera(args.camera), links=links,
                                                package_path=args.package_path, seed=args.seed)
        if not planned:
            raise BodySchemeError(f"no marker could be planned on {args.robot}: " + "; ".join(
                f"{link}: {why}" for link, why in skipped.items()))
        markers = write_markers(planned, out / "markers.yaml")
        sheet = write_sheet([p.marker for p in planned], out / "markers", dpi=args.dpi)
        params = write_scheme_parameters(args.robot, markers, scheme_parameters_path(markers))
        camera_file = write_camera(camera, beside_markers(markers, "camera.yaml"))
    except (OSError, BodySchemeError) as error:
        print(f"plan_markers: {error}", file=sys.stderr)
        return 1
    print(f"{'id':>4s}  {'link':24s} {'size mm':>8s}  seen")
    for p in planned:
        print(f"{p.marker.id:4d}  {p.marker.link:24s} {1000 * p.marker.size:8.0f}  "
              f"{100 * p.visible:3.0f} % of postures")
    for link, why in skipped.items():
        print(f"      {link:24s} no marker: {why}")
    print(f"wrote {markers}, {', '.join(str(p) for p in sheet)}, {camera_file} and {params} (scheme_node's "
          f"parameters for this robot: --params-file)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
