"""The joint fit: the root pose and every local model of the tree against absolute observations.

The paper fits each local model on its own (Sec. III-B); the joint fit refines the whole tree at once, as a kinematic
calibration does (robot_calibration's chain optimisation), and leaves the parameters' covariance with the body scheme
(:mod:`.joint_fit`). Its residuals test whether the scheme explains every marker (:mod:`.consistency`) and teach the
learner the camera's noise (:mod:`.noise_model`). How accurate the result is, on poses no fit saw:
:mod:`.cross_validation`.
"""

from __future__ import annotations

from .consistency import (
    CLIP,
    MIN_EXPLAINED,
    MIN_EXTRA_SAMPLES,
    PartConsistency,
    action_features,
    lack_of_fit,
    part_consistency,
)
from .cross_validation import (
    CrossValidation,
    accuracy_report,
    cross_validate,
    fold_indices,
    jackknife_std,
    refit_scheme,
)
from .fit_problem import covariance_whitening
from .joint_fit import Calibration, calibrate, chain_targets, edge_consistency
from .noise_model import NoiseModel, ray_components, robust_variance

__all__ = [
    "Calibration",
    "CrossValidation",
    "accuracy_report",
    "cross_validate",
    "fold_indices",
    "jackknife_std",
    "refit_scheme",
    "calibrate",
    "covariance_whitening",
    "chain_targets",
    "edge_consistency",
    "CLIP",
    "MIN_EXTRA_SAMPLES",
    "MIN_EXPLAINED",
    "PartConsistency",
    "action_features",
    "lack_of_fit",
    "part_consistency",
    "NoiseModel",
    "robust_variance",
    "ray_components",
]
