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
``perception_<camera>_<target>_<distance>m_{lateral_mm, depth_mm, depth_p90_mm, rot_deg, flip_rate}``
    A Monte Carlo of the pose from noisy corners (no rendering; :func:`corner_noise_study`): a 640x480 (60 deg) and a
    1280x720 (69 deg) camera, 1, 1.5 and 2 m, one 8 cm tag (``tag``) or a plate of 2 x 2 such tags 2 cm apart
    (``plate``, :func:`~body_scheme_core.plates.plate_pose`), tilted 0-60 deg, 0.3 px of corner noise: median
    error across the ray, along it (and its 90th percentile), median rotation error of the poses not mirrored, and
    the fraction mirrored (rotation error above 20 deg).

The process is pinned to one CPU and OpenCV / BLAS to one thread before anything heavy is imported.
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from body_scheme_apps.bench_output import report  # noqa: E402
from body_scheme_core.perception import MarkerTracker  # noqa: E402
from body_scheme_core.plates import grid_plate, plate_pose  # noqa: E402
from body_scheme_core.world import babble  # noqa: E402
from body_scheme_sim.babbling import babbling_screen  # noqa: E402
from body_scheme_sim.sessions import PROTOCOL_MARKERS_OF_INTEREST, record_session  # noqa: E402
from body_scheme_sim.world import SimWorld  # noqa: E402

from .entry import command  # noqa: E402

__all__ = ["TARGETS", "CAMERAS", "run_benchmarks", "corner_noise_study", "main"]

#: Minimum rates the simulator and the tracker must reach on one core, Hz.
TARGETS = {"sim_render_hz": 30.0, "tracker_hz": 60.0}


#: The cameras of the corner-noise study: width, height (px), horizontal field of view (rad).
CAMERAS = {"640x480": (640, 480, math.radians(60.0)), "1280x720": (1280, 720, math.radians(69.0))}
#: Distances (m), targets, tag edge (m), gap between a plate's tags (m), corner noise (px) of the study.
STUDY_DISTANCES, STUDY_TARGETS = (1.0, 1.5, 2.0), ("tag", "plate")
STUDY_TAG, STUDY_GAP, STUDY_SIGMA_PX = 0.08, 0.02, 0.3


def _camera_matrix(width, height, hfov):
    f = 0.5 * width / math.tan(0.5 * hfov)
    return np.array([[f, 0.0, 0.5 * (width - 1)], [0.0, f, 0.5 * (height - 1)], [0.0, 0.0, 1.0]])


def _study_cell(camera_matrix, distance, plate, trials, rng):
    """Errors of ``trials`` poses of ``plate`` at ``distance``: lateral, depth (m), rotation (rad)."""
    errors = []
    for _ in range(trials):
        tilt, azimuth = rng.uniform(0.0, math.radians(60.0)), rng.uniform(0.0, 2.0 * math.pi)
        R = (np.diag([1.0, -1.0, -1.0])  # facing the camera, then tilted and turned about its normal
             @ Rotation.from_rotvec(tilt * np.array([math.cos(azimuth), math.sin(azimuth), 0.0])).as_matrix()
             @ Rotation.from_rotvec([0.0, 0.0, rng.uniform(-math.pi, math.pi)]).as_matrix())
        t = np.array([rng.uniform(-0.3, 0.3) * distance, rng.uniform(-0.2, 0.2) * distance, distance])
        corners = {}
        for tag_id in plate.tags:
            projected, _ = cv2.projectPoints(plate.corners(tag_id), cv2.Rodrigues(R)[0], t, camera_matrix, None)
            corners[tag_id] = projected.reshape(4, 2) + rng.normal(0.0, STUDY_SIGMA_PX, (4, 2))
        pose = plate_pose(plate, corners, camera_matrix).pose
        ray, offset = t / np.linalg.norm(t), pose[:3, 3] - t
        errors.append((np.linalg.norm(offset - (offset @ ray) * ray), abs(offset @ ray),
                       Rotation.from_matrix(pose[:3, :3].T @ R).magnitude()))
    return np.array(errors)


def corner_noise_study(trials=300, seed=0):
    """``{perception_<camera>_<target>_<distance>m_<figure>: value}`` (module docstring)."""
    rng = np.random.default_rng(seed)
    plates = {"tag": grid_plate([1], STUDY_TAG, STUDY_GAP), "plate": grid_plate([1, 2, 3, 4], STUDY_TAG, STUDY_GAP)}
    figures = {}
    for camera, spec in CAMERAS.items():
        K = _camera_matrix(*spec)
        for distance in STUDY_DISTANCES:
            for target in STUDY_TARGETS:
                lateral, depth, rotation = _study_cell(K, distance, plates[target], trials, rng).T
                mirrored = rotation > math.radians(20.0)
                key = f"perception_{camera}_{target}_{distance:g}m"
                figures.update({f"{key}_lateral_mm": float(1e3 * np.median(lateral)),
                                f"{key}_depth_mm": float(1e3 * np.median(depth)),
                                f"{key}_depth_p90_mm": float(1e3 * np.percentile(depth, 90)),
                                f"{key}_rot_deg": float(np.degrees(np.median(rotation[~mirrored]))),
                                f"{key}_flip_rate": float(np.mean(mirrored))})
    return figures


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


def run_benchmarks(n_frames=200, n_steps=300, seed=0, trials=300):
    """Run every measurement; returns the result dictionary written to ``sim.json``."""
    pinning = _pin_one_core()
    study = corner_noise_study(trials, seed)
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
        **study,
        "corner_noise_trials": int(trials),
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
        "",
        f"corner noise {STUDY_SIGMA_PX} px, {result['corner_noise_trials']} poses per cell, tilt 0-60 deg:",
        f"{'camera / target / distance':32s} {'lateral mm':>10s} {'depth mm':>9s} {'p90':>6s} {'rot deg':>8s} "
        f"{'mirrored':>8s}",
    ]
    for camera in CAMERAS:
        for distance in STUDY_DISTANCES:
            for target in STUDY_TARGETS:
                key = f"perception_{camera}_{target}_{distance:g}m"
                cell = f"{camera} / {target} / {distance:g} m"
                lines.append(f"{cell:32s} {result[key + '_lateral_mm']:10.2f} "
                             f"{result[key + '_depth_mm']:9.1f} {result[key + '_depth_p90_mm']:6.1f} "
                             f"{result[key + '_rot_deg']:8.2f} {result[key + '_flip_rate']:8.3f}")
    return "\n".join(lines)


@command
def main(argv=None):
    """Console entry point: run, print a table, write the JSON file."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.perception_bench",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join("out", "bench", "sim.json"),
                        help="JSON file to write (directories are created; default: %(default)s)")
    parser.add_argument("--frames", type=int, default=200, help="frames for the rates (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=300, help="steps of the accuracy session (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trials", type=int, default=300,
                        help="poses per cell of the corner-noise study (default: %(default)s)")
    parser.add_argument("--copy", default=None, help="also write the JSON here (make bench UPDATE_RESULTS=1: "
                        "docs/results/sim.json, which docs/sim.md quotes)")
    args = parser.parse_args(argv)
    result = run_benchmarks(n_frames=args.frames, n_steps=args.steps, seed=args.seed, trials=args.trials)
    if args.copy:
        report(result, "", args.copy)
    return report(result, _table(result), args.out)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
