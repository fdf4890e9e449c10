"""``record_session``: record a babbling session of the simulator into a rosbag2 (mcap) directory.

Examples::

    record_session --protocol joint_blocked --seed 0 --out bags/joint_blocked_seed0
    record_session --robot planar_2dof --steps 200 --fault 100:block_joint:1:0.3 --out /tmp/planar
    record_session --steps 30 --perception rendered --images 10 --out /tmp/rendered
    record_session --robot path/to/robot.urdf --steps 300 --out /tmp/mine   # markers planned: /tmp/mine.markers.yaml
                                                   # (and scheme_node's parameters: /tmp/mine.scheme_node.yaml)

The bag layout is documented in :mod:`body_scheme_nodes.bag_io`.
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys

from tqdm import tqdm

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.world import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS
from body_scheme_nodes.bag_io import write_session
from body_scheme_sim.sessions import (
    PERCEPTION_MODES,
    PROTOCOL_MARKERS_OF_INTEREST,
    PROTOCOLS,
    protocol_faults,
    record_session,
)

from .entry import command
from .robot_option import add_robot_arguments, resolve_robot

__all__ = ["main", "parser"]


def parser():
    """The command-line interface."""
    p = argparse.ArgumentParser(prog="record_session", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_robot_arguments(p)
    p.add_argument("--steps", type=int, default=None,
                   help="number of commands (default: 4 blocks of --block-size with a protocol, else 400)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--protocol", choices=["none", *PROTOCOLS], default="none",
                   help="the paper's fault protocols (4 blocks: normal, fault, repaired, fault); powercube_6dof only")
    p.add_argument("--block-size", type=int, default=100, help="steps per protocol block")
    p.add_argument("--fault", action="append", default=[], metavar="STEP:KIND:ARGS",
                   help="fault schedule entry (repeatable), e.g. 150:block_joint:5:0.8 or 250:repair")
    p.add_argument("--perception", choices=PERCEPTION_MODES, default="noise")
    p.add_argument("--sigma-trans", type=float, default=PAPER_SIGMA_TRANS, help="noise mode: m")
    p.add_argument("--sigma-rot", type=float, default=math.degrees(PAPER_SIGMA_ROT), help="noise mode: degrees")
    p.add_argument("--visibility", type=float, default=1.0,
                   help="noise mode: probability that a visible marker is observed")
    p.add_argument("--markers-of-interest", type=int, nargs="*", default=None,
                   help="markers that must be visible in every babbled configuration "
                        f"(default: {list(PROTOCOL_MARKERS_OF_INTEREST)} with a protocol, else none)")
    p.add_argument("--images", type=int, default=0, metavar="N",
                   help="store every N-th camera image in the bag (0: none)")
    p.add_argument("--period", type=float, default=0.1, help="seconds between commands")
    p.add_argument("--out", required=True, help="bag directory to create (must not exist)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


@command
def main(argv=None):
    """Record a session and write its bag; returns the exit code (0 ok, 1 error)."""
    args = parser().parse_args(argv)
    faults = list(args.fault)
    markers_of_interest = args.markers_of_interest
    n_steps = args.steps
    if args.protocol != "none":
        if args.robot != "powercube_6dof":
            print(f"record_session: protocol {args.protocol} is defined on powercube_6dof only", file=sys.stderr)
            return 1
        faults = protocol_faults(args.protocol, args.block_size) + faults
        markers_of_interest = PROTOCOL_MARKERS_OF_INTEREST if markers_of_interest is None else markers_of_interest
        n_steps = 4 * args.block_size if n_steps is None else n_steps
    n_steps = 400 if n_steps is None else n_steps
    try:
        choice = resolve_robot(args.robot, args.markers, args.camera, args.package_path,
                               pathlib.Path(f"{args.out}.markers.yaml"), args.seed)
    except BodySchemeError as error:
        print(f"record_session: {error}", file=sys.stderr)
        return 1
    with tqdm(total=n_steps, desc=f"recording {args.out}", unit="step", disable=args.quiet) as bar:
        try:
            session = record_session(
                choice.robot, n_steps, args.seed, faults=faults, perception=args.perception,
                camera=choice.camera, markers_path=choice.markers_path, package_path=choice.package_path,
                sigma_trans=args.sigma_trans, sigma_rot=math.radians(args.sigma_rot), visibility=args.visibility,
                image_every=args.images, markers_of_interest=markers_of_interest, period=args.period,
                protocol=args.protocol, progress=lambda done: bar.update(done - bar.n))
            path = write_session(session, args.out)
        except BodySchemeError as error:
            bar.close()
            print(f"record_session: {error}", file=sys.stderr)
            return 1
    seen = session.visible.mean() if session.n_steps else 0.0
    print(f"wrote {path}: {session.n_steps} steps, {len(session.images)} images, faults {session.faults}, "
          f"markers observed {100 * seen:.1f}% of the time")
    return 0


if __name__ == "__main__":
    sys.exit(main())
