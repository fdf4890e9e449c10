"""Real arms' data (not in the paper): two public datasets of real arms observed at the tool, learned through the
core API.

The datasets are read from ``../shared/realdata`` beside the repository (or ``BODY_SCHEME_REALDATA``); they carry no
licence, so they are never copied into the project, and without them this experiment prints that it skipped them and
reports nothing but ``realdata_available`` 0. Each line of their JSON-lines files is one pose: joint values (``q``,
``q_units``) and 6D poses of the observed bodies in the sensor's frame (their README). Both are tool-only set-ups:
the sensor stands still relative to the robot's base and sees one body on the tool, so the learner takes the sensor as
the root (``sensor_root``): parts ``0`` (the sensor) and ``1`` (the tool).

- ``fanuc``: an industrial 6-axis arm measured by a laser tracker, one joint swept at a time (the shoulder and elbow
  commands together in some poses: the arm couples them). From scratch.
- ``tiago``: a mobile manipulator's prismatic torso and 7-joint arm, a motion-capture body on the hand, static postures
  in random order (no joint ever moves alone). With the robot's public URDF as the prior
  (:data:`TIAGO_URDF`, PAL Robotics, Apache-2.0; the motion-capture bodies' places are registered first,
  :func:`~body_scheme_core.learning.register_chain`), and from scratch (reported: without excursions
  no chain can be identified).

Protocol: the poses are split once, a fixed 80 % for training (in their recorded order) and 20 % to test (the
permutation of seed 0); the learner learns the training poses, and the *held-out error* is the mean distance between
the predicted and the measured tool position at the test poses. The *cross-validated error* (``_cv_mm``) is what
``calibrate`` reports a user (:func:`~body_scheme_core.calibration.cross_validate`): 5 folds, each pose predicted once
by the same procedure run on the other 80 %, and next to it the nominal model's (TIAGo: its URDF, the bodies' places
registered per fold); not with ``--quick``. Noise priors: the laser tracker 0.1 mm / 0.05 deg,
motion capture 1 mm / 0.5 deg (3D RMS).
"""

from __future__ import annotations

import json
import math
import os
import pathlib

import numpy as np

from body_scheme_core.calibration import cross_validate
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner, register_chain
from body_scheme_core.models import EngineeredModel, chain_from_engineered
from body_scheme_core.world import KinematicTree, Marker

__all__ = ["FIGURES", "PAPER", "TARGETS", "MIN_TARGETS", "SANITY", "RUNS", "PERCEPTIONS", "run", "summarize", "plot",
           "read_poses", "realdata_dir"]

RUNS = 1
PERCEPTIONS = ("noise",)
TIAGO_URDF = pathlib.Path(__file__).resolve().parent / "data" / "tiago_torso_arm.urdf"
#: Dataset -> (file, observed body, noise prior (3D RMS m, rad)).
DATASETS = {"fanuc": ("fanuc_laser.jsonl", "smr_nest", (1e-4, math.radians(0.05))),
            "tiago": ("tiago_mocap.jsonl", "hand_body", (1e-3, math.radians(0.5)))}
TRAIN_FRACTION = 0.8
CV_FOLDS = 5
#: The prior: how far each joint of the real TIAGo may be from its URDF (m, rad per axis).
TIAGO_PRIOR = (0.003, math.radians(1.0))

FIGURES = {
    "realdata_available": "1 when ../shared/realdata was found and evaluated",
    "realdata_fanuc_heldout_mm": "Fanuc, laser tracker, from scratch: mean tool position error at the 20 % test poses "
                                 "(mm)",
    "realdata_fanuc_train_mm": "Fanuc: the same on the training poses (mm)",
    "realdata_tiago_heldout_mm": "TIAGo arm, motion capture, the URDF as the prior: mean hand position error at the "
                                 "test poses (mm)",
    "realdata_tiago_nominal_mm": "TIAGo: the URDF alone, its bodies' places registered on the training poses (mm)",
    "realdata_tiago_scratch_has_scheme": "TIAGo from scratch: 1 when the learner ends with a body scheme",
    "realdata_fanuc_cv_mm": "Fanuc, from scratch: 5-fold cross-validated mean tool position error (mm)",
    "realdata_fanuc_cv_failed_folds": "Fanuc: folds whose training poses gave no body scheme",
    "realdata_tiago_cv_mm": "TIAGo, the URDF as the prior: 5-fold cross-validated mean hand position error (mm)",
    "realdata_tiago_nominal_cv_mm": "TIAGo: the same for the URDF alone, its bodies registered per fold (mm)",
}
PAPER = {}
TARGETS = {"realdata_fanuc_heldout_mm": 1.0, "realdata_tiago_heldout_mm": 5.0}
MIN_TARGETS = {}
SANITY = {}
NOTES = ("The TIAGo copy holds the postures of a session its authors later replaced: 16 of its 34 rows were sampled "
         "while the arm still moved (errors up to 7.8 mm), and one of the hand body's four markers is a copy of "
         "another; its floor is a few mm whatever the model (figaroh's full calibration: 2.7 mm RMS in-sample).")


def realdata_dir():
    """Where the datasets are: ``BODY_SCHEME_REALDATA``, else ``../shared/realdata`` from the working directory."""
    return pathlib.Path(os.environ.get("BODY_SCHEME_REALDATA", pathlib.Path.cwd().parent / "shared" / "realdata"))


def read_poses(path, body):
    """``(q (n, m) in rad and m, tool poses (n, 4, 4))`` of a JSON-lines dataset (its README's format)."""
    rows = [json.loads(line) for line in pathlib.Path(path).read_text().splitlines() if line.strip()]
    q = np.array([r["q"] for r in rows], dtype=float)
    if rows[0]["q_units"] == "deg":
        q = np.radians(q)
    return q, np.array([r["markers"][body]["T"] for r in rows], dtype=float)


def _split(n):
    order = np.random.default_rng(0).permutation(n)
    k = int(round(TRAIN_FRACTION * n))
    return np.sort(order[:k]), np.sort(order[k:])


def _learner(n_actions, noise, initial=None):
    # A laser tracker and motion capture have no planar-marker ambiguity: no mirrored readings.
    config = BodySchemeConfig(root=0, sensor_root=True, mirror_hypotheses=False,
                              **({} if noise is None else {"sigma_trans": noise[0], "sigma_rot": noise[1]}))
    return BodySchemeLearner([0, 1], n_actions, config, initial_models=initial)


def _errors_mm(learner, q, Z):
    if learner.body_scheme is None:
        return None
    return 1e3 * np.array([np.linalg.norm(learner.predict(a)[1][:3, 3] - T[:3, 3]) for a, T in zip(q, Z,
                                                                                                     strict=True)])


def _learn(learner, q, Z):
    for a, T in zip(q, Z, strict=True):
        learner.update(a, {1: T})
    return learner


def _predictor(learner):
    """``a -> {1: sensor2tool}`` of a learner with a body scheme, else None (for cross_validate)."""
    return None if learner.body_scheme is None else learner.predict


def _cv_mm(fit, q, Z):
    cv = cross_validate(fit, q, [{1: T} for T in Z], folds=CV_FOLDS, parts=[1])
    return cv.mean_mm if not cv.failed_folds else math.inf, cv.failed_folds


def run(seed, perception="noise", quick=False):
    """Evaluate both datasets (one run: the split is fixed); see the module docstring."""
    directory = realdata_dir()
    if not all((directory / name).is_file() for name, _, _ in DATASETS.values()):
        print(f"realdata: {directory} holds no datasets: skipped")
        return {"realdata_available": 0.0, "curves": {}, "events": []}
    out = {"realdata_available": 1.0, "curves": {}, "events": []}
    name, body, noise = DATASETS["fanuc"]
    q, Z = read_poses(directory / name, body)
    train, test = _split(len(q))
    learner = _learn(_learner(q.shape[1], noise), q[train], Z[train])
    held, trained = _errors_mm(learner, q[test], Z[test]), _errors_mm(learner, q[train], Z[train])
    out["realdata_fanuc_heldout_mm"] = math.inf if held is None else float(held.mean())
    out["realdata_fanuc_train_mm"] = math.inf if trained is None else float(trained.mean())
    if not quick:  # five more learners from scratch (about 2 min)
        out["realdata_fanuc_cv_mm"], failed = _cv_mm(
            lambda rows: _predictor(_learn(_learner(q.shape[1], noise), q[rows], Z[rows])), q, Z)
        out["realdata_fanuc_cv_failed_folds"] = float(failed)
    name, body, noise = DATASETS["tiago"]
    q, Z = read_poses(directory / name, body)
    train, test = _split(len(q))
    tree = KinematicTree.from_urdf(TIAGO_URDF.read_text(), markers=[Marker(0, "base_footprint", np.eye(4)),
                                                                    Marker(1, "wrist_ft_tool_link", np.eye(4))])

    def specification(rows):
        spec = chain_from_engineered(EngineeredModel.from_tree(tree, 0, 1), reference=np.median(q[rows], axis=0),
                                     prior=TIAGO_PRIOR, sigma_trans=noise[0], sigma_rot=noise[1])
        return register_chain(spec, q[rows], Z[rows], (noise[0] / math.sqrt(3), noise[1] / math.sqrt(3)))

    def with_prior(rows):
        learner = _learn(_learner(q.shape[1], noise, initial=[specification(rows)]), q[rows], Z[rows])
        learner.recalibrate()  # the joint fit on every training pose
        return learner

    spec = specification(train)
    nominal = 1e3 * np.linalg.norm(spec.predict(q[test])[:, :3, 3] - Z[test, :3, 3], axis=1)
    learner = with_prior(train)
    held = _errors_mm(learner, q[test], Z[test])

    def registered(rows):
        spec = specification(rows)
        return lambda a: {1: spec.predict(np.asarray(a)[None, :])[0]}

    if not quick:
        out["realdata_tiago_cv_mm"], _ = _cv_mm(lambda rows: _predictor(with_prior(rows)), q, Z)
        out["realdata_tiago_nominal_cv_mm"], _ = _cv_mm(registered, q, Z)
    out["realdata_tiago_heldout_mm"] = math.inf if held is None else float(held.mean())
    out["realdata_tiago_nominal_mm"] = float(nominal.mean())
    scratch = _learn(_learner(q.shape[1], noise), q[train], Z[train])
    out["realdata_tiago_scratch_has_scheme"] = float(scratch.body_scheme is not None)
    return out


def summarize(runs):
    """The one run's figures."""
    return {k: float(v) for r in runs[:1] for k, v in r.items() if k not in ("curves", "events")}


def plot(runs, path_prefix):
    """No plot: a handful of figures."""
    return []
