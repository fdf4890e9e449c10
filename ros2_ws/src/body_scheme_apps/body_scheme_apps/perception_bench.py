"""Simulator and tracker benchmark: rates on one core, tracker accuracy and visibility on a babbling session.

Measures (all on ``powercube_6dof`` with the default 640x480 camera about 2 m away):

``sim_render_hz``
    ``SimWorld.execute`` of a random command plus ``SimWorld.render`` per second (target >= 30).
``tracker_hz``
    ``MarkerTracker.detect`` calls per second on rendered frames of babbling configurations (target >= 60).
``tracker_trans_err_mm``, ``tracker_rot_err_deg``
    Median and 90th percentile of the distance and rotation angle between each tracked marker pose and its ground
    truth, over a rendered babbling session (markers 6 and 7 of interest, as in the paper's protocols).
``mirrored_pose_rate``, ``per_marker_errors``
    Fraction of poses with a rotation error above 20 deg (IPPE's mirrored solution), and errors by marker id.
``visibility_rate``
    ``detected``: fraction of the robot's markers the tracker returns a pose for, per frame, averaged;
    ``geometric``: the same for ``SimWorld.visible_marker_ids`` (in view, facing the camera, not occluded);
    ``detected_of_visible``: fraction of geometrically visible markers the tracker finds; ``per_marker``: detected
    rate by marker id.

The process is pinned to one CPU and OpenCV / BLAS to one thread before anything heavy is imported.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from body_scheme_apps.bench_output import report  # noqa: E402
from body_scheme_core.perception import MarkerTracker  # noqa: E402
from body_scheme_core.world import babble  # noqa: E402
from body_scheme_sim.babbling import babbling_screen  # noqa: E402
from body_scheme_sim.sessions import PROTOCOL_MARKERS_OF_INTEREST, record_session  # noqa: E402
from body_scheme_sim.world import SimWorld  # noqa: E402

__all__ = ["TARGETS", "run_benchmarks", "main"]

#: Minimum rates the simulator and the tracker must reach on one core, Hz.
TARGETS = {"sim_render_hz": 30.0, "tracker_hz": 60.0}


def _pin_one_core():
    """Run on one CPU (the first this process may use); returns a note saying how."""
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"sched_setaffinity to CPU {cpu}, cv2.setNumThreads(1)"
    return "cv2.setNumThreads(1) (no CPU affinity on this platform)"


def _per_marker_errors(session):
    """``{id: {trans_mm_median, rot_deg_median, rot_deg_p90}}`` of every tracked marker."""
    result = {}
    for marker_id in session.marker_ids:
        errors = session.observation_errors({marker_id})
        if errors.shape[0]:
            result[str(marker_id)] = {"trans_mm_median": float(1e3 * np.median(errors[:, 0])),
                                      "rot_deg_median": float(np.degrees(np.median(errors[:, 1]))),
                                      "rot_deg_p90": float(np.degrees(np.percentile(errors[:, 1], 90)))}
    return result


def _rates(n_frames, seed):
    """``(sim_render_hz, tracker_hz)`` over ``n_frames`` babbled configurations."""
    with SimWorld(seed=seed) as world:
        actions = babble(world, n_frames, np.random.default_rng(seed), screen=babbling_screen(world))
        world.render()  # the static backdrop is rendered once per camera: not part of the per-frame cost
        frames = []
        start = time.perf_counter()
        for a in actions:
            world.execute(a)
            frames.append(world.render())
        render_hz = n_frames / (time.perf_counter() - start)
        sizes = {marker_id: world.robot.marker(marker_id).size for marker_id in world.marker_ids}
        tracker = MarkerTracker(world.camera.K, marker_sizes=sizes)
    tracker.detect(frames[0])
    start = time.perf_counter()
    for image in frames:
        tracker.detect(image)
    tracker_hz = n_frames / (time.perf_counter() - start)
    return render_hz, tracker_hz


def _visibility(session):
    n_markers = len(session.marker_ids)
    detected = session.visible
    geometric = session.visible_truth
    return {
        "detected": float(detected.sum() / (session.n_steps * n_markers)),
        "geometric": float(geometric.sum() / (session.n_steps * n_markers)),
        "detected_of_visible": float((detected & geometric).sum() / max(geometric.sum(), 1)),
        "per_marker": {str(marker_id): float(detected[:, j].mean()) for j, marker_id in enumerate(session.marker_ids)},
    }


def run_benchmarks(n_frames=200, n_steps=300, seed=0):
    """Run every measurement; returns the result dictionary written to ``sim.json``."""
    pinning = _pin_one_core()
    render_hz, tracker_hz = _rates(n_frames, seed)
    session = record_session("powercube_6dof", n_steps, seed, perception="rendered",
                             markers_of_interest=PROTOCOL_MARKERS_OF_INTEREST)
    errors = session.observation_errors()
    trans_mm, rot_deg = 1e3 * errors[:, 0], np.degrees(errors[:, 1])
    return {
        "sim_render_hz": float(render_hz),
        "tracker_hz": float(tracker_hz),
        "targets": dict(TARGETS),
        "meets_targets": bool(render_hz >= TARGETS["sim_render_hz"] and tracker_hz >= TARGETS["tracker_hz"]),
        "tracker_trans_err_mm": {"median": float(np.median(trans_mm)), "p90": float(np.percentile(trans_mm, 90))},
        "tracker_rot_err_deg": {"median": float(np.median(rot_deg)), "p90": float(np.percentile(rot_deg, 90))},
        "tracked_poses": int(errors.shape[0]),
        "mirrored_pose_rate": float(np.mean(rot_deg > 20.0)),
        "per_marker_errors": _per_marker_errors(session),
        "visibility_rate": _visibility(session),
        "tracker_rejected": session.tracker_rejected,
        "image_size": [session.camera.width, session.camera.height],
        "n_frames": int(n_frames),
        "n_steps": int(n_steps),
        "seed": int(seed),
        "pinning": pinning,
        "opencv": cv2.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def _table(result):
    visibility = result["visibility_rate"]
    trans, rot = result["tracker_trans_err_mm"], result["tracker_rot_err_deg"]
    lines = [
        f"{'measure':44s} {'value':>10s}  target",
        "-" * 64,
        f"{'sim step + 640x480 render (Hz)':44s} {result['sim_render_hz']:10.1f}  >= {TARGETS['sim_render_hz']:.0f}",
        f"{'tracker detect + pose (Hz)':44s} {result['tracker_hz']:10.1f}  >= {TARGETS['tracker_hz']:.0f}",
        f"{'tracker translation error median / p90 (mm)':44s} {trans['median']:5.1f} / {trans['p90']:5.1f}",
        f"{'tracker rotation error median / p90 (deg)':44s} {rot['median']:5.2f} / {rot['p90']:5.2f}",
        f"{'poses off by > 20 deg (mirrored)':44s} {result['mirrored_pose_rate']:10.3f}",
        f"{'markers detected per frame':44s} {visibility['detected']:10.3f}",
        f"{'markers geometrically visible per frame':44s} {visibility['geometric']:10.3f}",
        f"{'visible markers detected':44s} {visibility['detected_of_visible']:10.3f}",
        f"({result['tracked_poses']} poses over {result['n_steps']} rendered babbling steps; {result['pinning']})",
    ]
    return "\n".join(lines)


def main(argv=None):
    """Console entry point: run, print a table, write the JSON file."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.perception_bench",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join("out", "bench", "sim.json"),
                        help="JSON file to write (directories are created; default: %(default)s)")
    parser.add_argument("--frames", type=int, default=200, help="frames for the rates (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=300, help="steps of the accuracy session (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    result = run_benchmarks(n_frames=args.frames, n_steps=args.steps, seed=args.seed)
    return report(result, _table(result), args.out)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
