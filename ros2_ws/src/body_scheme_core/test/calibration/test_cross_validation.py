"""k-fold cross-validation: every observation predicted once, by a fit that never saw it."""

import math

import numpy as np
import pytest

from body_scheme_core.calibration import cross_validate, fold_indices, jackknife_std, refit_scheme
from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import make_session, planar_2dof


def test_the_folds_partition_the_poses():
    folds = fold_indices(23, folds=5, seed=1)
    assert len(folds) == 5 and sorted(np.concatenate(folds).tolist()) == list(range(23))
    assert all(4 <= len(f) <= 5 for f in folds)
    assert [f.tolist() for f in folds] == [f.tolist() for f in fold_indices(23, folds=5, seed=1)]
    for bad in (1, 24, 2.5, True):
        with pytest.raises(InvalidInputError):
            fold_indices(23, folds=bad)


def test_a_fit_that_memorises_its_training_poses_is_caught():
    """A predictor that is exact on training poses and wrong elsewhere scores its held-out error, not zero."""
    A = np.arange(20, dtype=float)[:, None]
    observations = [{1: transform_from_rotvec([0, 0, 0], [a, 0, 0])} for a in A[:, 0]]

    def fit(train):
        known = {float(A[k, 0]): observations[k][1] for k in train}
        return lambda a: {1: known.get(float(a[0]), transform_from_rotvec([0, 0, 0], [a[0] + 0.1, 0, 0]))}

    cv = cross_validate(fit, A, observations, folds=4)
    assert len(cv.trans[1]) == 20 and np.allclose(cv.trans[1], 0.1)
    assert cv.summary()[1]["mean_mm"] == pytest.approx(100.0) and cv.mean_mm == pytest.approx(100.0)
    failed = cross_validate(lambda train: None, A, observations, folds=4)
    assert failed.failed_folds == 4 and failed.trans == {} and math.isnan(failed.mean_mm)


def test_the_learned_scheme_refitted_is_as_accurate_on_held_out_poses_as_the_true_one():
    """On a noisy planar session, the learned structure refitted per fold predicts held-out poses as well as the
    exact specification (whose root pose alone is fitted): both at the observation noise (10 mm 3D RMS)."""
    robot = planar_2dof()
    sigma_t, sigma_r = 0.01, math.radians(3.0)
    session = make_session(robot, 80, seed=2, sigma_trans=sigma_t, sigma_rot=sigma_r)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(sigma_trans=sigma_t,
                                                                                    sigma_rot=sigma_r))
    for a, y in zip(session.actions, session.observations, strict=True):
        learner.update(a, y)
    learned = cross_validate(refit_scheme(learner.body_scheme, learner.root_pose, session.actions,
                                          session.observations, sigma_t, sigma_r), session.actions,
                             session.observations)
    nominal = BodyScheme(robot.marker_ids, robot.root_marker, engineered_models(robot))
    specified = cross_validate(refit_scheme(nominal, learner.root_pose, session.actions, session.observations,
                                            sigma_t, sigma_r), session.actions, session.observations)
    assert 5.0 < specified.mean_mm < 12.0
    assert learned.mean_mm < 1.15 * specified.mean_mm
    assert sum(s["n"] for p, s in learned.summary().items() if p != "all") == sum(map(len, session.observations))
    assert len(learned.fits) == 5 and all(hasattr(f, "scheme") for f in learned.fits)


def test_the_jackknife_std_of_fold_values():
    values = np.array([1.0, 2.0, 3.0, 4.0])
    assert jackknife_std(values) == pytest.approx(math.sqrt(3 / 4 * 5.0))
    with pytest.raises(InvalidInputError):
        jackknife_std([1.0])
