"""``calibrate``: the learned body scheme as URDF, and its calibration report against the robot's specification.

    python -m body_scheme_apps.calibrate --state STATE.json --joint-names j1,j2,... [--urdf NOMINAL.urdf
        --markers NOMINAL.markers.yaml] [--prefix robot1/] --out DIR
    python -m body_scheme_apps.calibrate --simulate ROBOT [--markers FILE] [--camera auto | "x y z r p y"]
        [--package-path DIR] [--perception rendered | noise] [--steps 600] --out DIR

``--state`` reads a state saved by scheme_node (``~/save``, checkpoints) or the core (``save_state``); ``--simulate``
learns one first from a babbling session in the simulator and compares it with the robot's specification. ``ROBOT``
is a shipped robot's name or any URDF path: its markers come from ``--markers``, else ``<stem>.markers.yaml`` beside
the URDF, else they are planned (:func:`body_scheme_sim.planning.plan_markers`, written to ``DIR/markers.yaml``).
The camera is ``--camera`` (default: the simulator's camera for a shipped robot, ``auto`` for a URDF: framing every
marker). ``rendered`` perception (the default) runs our ArUco tracker on the simulator's images; ``noise`` draws
observations at the rendered tracker's accuracy (10 mm, 5 deg). Writes to ``DIR``:

- ``learned.urdf``: :func:`body_scheme_core.prediction.learned_body.learned_urdf` (limits: the trained range);
- with a nominal robot: ``report.txt``, ``report.json`` (per joint ``axis_deg``, ``origin_mm``, ``marker_mm``,
  ``marker_deg``; ``max_*``) and ``report.png`` (the learned body against the nominal one at zero actions, and the
  deviations per joint).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np
from tqdm import tqdm

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.learning import load_state
from body_scheme_core.prediction import calibration_report, format_report, learned_tree, learned_urdf
from body_scheme_core.world import load_markers_yaml, tree_from_urdf

from .robot_option import add_camera_arguments, resolve_robot

__all__ = ["calibrate", "plot_report", "main"]


def calibrate(learner, joint_names, out, nominal=None, prefix=""):
    """Write ``learned.urdf`` (and, given the nominal ``KinematicTree``, the report files) to ``out``; returns the
    report (or None)."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scheme = learner.body_scheme
    if scheme is None:
        raise BodySchemeError(f"the state has no body scheme yet ({learner.phase}, step {learner.step})")
    body = learned_tree(scheme, joint_names, *learner.trained_range(), prefix=prefix, nominal=nominal)
    (out / "learned.urdf").write_text(learned_urdf(body))
    if nominal is None:
        return None
    report = calibration_report(body, nominal)
    (out / "report.txt").write_text(format_report(report) + "\n")
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    plot_report(body, nominal, report, out / "report.png")
    return report


def plot_report(body, nominal, report, path):
    """The learned body (colour) against the nominal one (grey) in a bent configuration (half of each joint's upper
    limit), in the root marker's frame, with the learned joint axes; and the per-joint deviations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bent = 0.5 * np.nan_to_num(np.asarray(nominal.action_upper, dtype=float))
    learned = body.marker_poses(bent[:body.n_actions])
    specified = nominal.marker_poses(bent)
    root = min(learned, key=lambda p: np.linalg.norm(learned[p][:3, 3]))
    to_root = np.linalg.inv(specified[root])
    truth = {p: to_root @ T for p, T in specified.items() if p in learned}
    fig = plt.figure(figsize=(11, 4.8))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for joint in body.joints:
        for poses, style in ((truth, dict(color="0.6", lw=5, alpha=0.6)), (learned, dict(color="tab:blue", lw=2))):
            a, b = poses[joint.parent][:3, 3], poses[joint.child][:3, 3]
            ax.plot(*zip(a, b, strict=True), **style)
        if joint.type == "revolute":
            point = learned[joint.parent] @ np.append(joint.point, 1.0)
            axis = learned[joint.parent][:3, :3] @ np.asarray(joint.axis)
            ax.quiver(*point[:3], *(0.12 * axis), color="tab:red")
    for p, T in learned.items():
        ax.text(*T[:3, 3], f" {p}", fontsize=8)
    ax.set_title("learned (blue, red: joint axes) vs specification (grey)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_box_aspect((1, 1, 1))
    span = max(np.ptp([T[:3, 3] for T in truth.values()], axis=0).max(), 0.2)
    centre = np.mean([T[:3, 3] for T in truth.values()], axis=0)
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
        setter(c - span / 2, c + span / 2)
    bars = fig.add_subplot(1, 2, 2)
    rows = report["joints"]
    x = np.arange(len(rows))
    bars.bar(x - 0.2, [r["axis_deg"] for r in rows], 0.4, label="axis (deg)")
    bars.bar(x + 0.2, [r["origin_mm"] or 0.0 for r in rows], 0.4, label="origin (mm)")
    bars.set_xticks(x, [r["nominal_joint"] for r in rows], rotation=30)
    bars.axhline(2.0, color="tab:blue", ls=":", lw=1)
    bars.axhline(5.0, color="tab:orange", ls=":", lw=1)
    bars.set_title("deviation from the specification per joint")
    bars.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _simulated(choice, steps, seed, perception="rendered"):
    """A learner taught by a babbling session in the simulator (:class:`~body_scheme_apps.robot_option.RobotChoice`),
    and the robot's nominal tree."""
    from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
    from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS, record_session

    nominal = choice.tree
    with tqdm(total=steps, desc="babbling in the simulator", unit="step", disable=not sys.stderr.isatty()) as bar:
        session = record_session(choice.robot, n_steps=steps, seed=seed, sigma_trans=RENDERED_SIGMA_TRANS,
                                 sigma_rot=RENDERED_SIGMA_ROT, perception=perception, camera=choice.camera,
                                 markers_path=choice.markers_path, package_path=choice.package_path,
                                 progress=lambda done: bar.update(done - bar.n))
    # The noise priors of the tracker on rendered images (as live_demo): its errors are heavy-tailed, and the
    # default "auto" prior, replaced by the first robust estimate, makes the thresholds too tight for them.
    config = BodySchemeConfig(sigma_trans=RENDERED_SIGMA_TRANS, sigma_rot=RENDERED_SIGMA_ROT)
    learner = BodySchemeLearner(nominal.marker_ids, nominal.n_actions, config, action_lower=nominal.action_lower,
                                action_upper=nominal.action_upper)
    for actions, observations in zip(session.actions, session.observations, strict=True):
        learner.update(actions, observations)
    return learner, nominal


def main(argv=None):
    """Console entry point; exit code 1 with a one-line error for unreadable input."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.calibrate", description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--state", help="learner state file (scheme_node ~/save or checkpoint)")
    source.add_argument("--simulate", metavar="ROBOT", help="learn from the simulator first: a shipped robot's name "
                                                             "or a URDF path")
    parser.add_argument("--joint-names", help="comma-separated joint names in action order (default: the nominal "
                                              "URDF's, else joint_0, joint_1, ...)")
    parser.add_argument("--urdf", help="nominal URDF of the robot (with --markers): write the calibration report")
    parser.add_argument("--markers", help="nominal marker placement YAML (with --simulate: the markers to simulate; "
                                          "default: beside the URDF, else planned into --out)")
    parser.add_argument("--prefix", default="", help="prefix of link names (joints keep the robot's)")
    parser.add_argument("--steps", type=int, default=600, help="--simulate: babbling steps (default: %(default)s)")
    add_camera_arguments(parser, prefix="--simulate: ")
    parser.add_argument("--perception", choices=("rendered", "noise"), default="rendered",
                        help="--simulate: our tracker on rendered images, or noise at its accuracy "
                             "(default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output directory")
    args = parser.parse_args(argv)
    try:
        if args.simulate:
            choice = resolve_robot(args.simulate, args.markers, args.camera, args.package_path,
                                   pathlib.Path(args.out) / "markers.yaml", args.seed)
            learner, nominal = _simulated(choice, args.steps, args.seed, args.perception)
        else:
            learner = load_state(args.state)
            nominal = None
            if args.urdf or args.markers:
                if not (args.urdf and args.markers):
                    parser.error("--urdf and --markers go together")
                nominal = tree_from_urdf(pathlib.Path(args.urdf).read_bytes(), load_markers_yaml(args.markers))
        names = (args.joint_names.split(",") if args.joint_names else
                 list(nominal.action_joint_names) if nominal is not None else
                 [f"joint_{k}" for k in range(learner.n_actions)])
        report = calibrate(learner, names, args.out, nominal, args.prefix)
    except (OSError, BodySchemeError) as error:
        print(f"calibrate: {error}", file=sys.stderr)
        return 1
    print(f"wrote {pathlib.Path(args.out) / 'learned.urdf'}")
    if report is not None:
        print(format_report(report))
        print(f"max: axis {report['max_axis_deg']:.3f} deg, origin {report['max_origin_mm']:.2f} mm, marker "
              f"{report['max_marker_mm']:.2f} mm; wrote report.txt, report.json, report.png in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
