"""The body scheme and what it predicts (paper Sec. III-C/D, Eq. 8).

:class:`BodyScheme` chains the local models of a spanning tree from the root part to predict every part's pose for
an action vector, with its propagated uncertainty (:mod:`.scheme`), and its Jacobian (Eq. 10, :mod:`.jacobian`);
:mod:`.uncertainty` carries the joint fit's covariance to a part's position; :mod:`.learned_body` writes the learned
body as a robot description (URDF) and compares it with the robot's specification; :mod:`.calibrated_urdf` writes the
robot's own URDF with the learned joint axes (a drop-in replacement).
"""

from __future__ import annotations

from .calibrated_urdf import CalibratedURDF, calibrated_urdf, format_diff
from .learned_body import (
    LearnedBody,
    LearnedJoint,
    calibration_report,
    format_report,
    learned_tree,
    learned_urdf,
    marker_link,
)
from .scheme import BodyScheme
from .uncertainty import error_radius, parameter_jacobian, perturbed_models, position_covariance, position_std

__all__ = [
    "BodyScheme",
    "error_radius",
    "parameter_jacobian",
    "perturbed_models",
    "position_covariance",
    "position_std",
    "LearnedJoint",
    "LearnedBody",
    "marker_link",
    "learned_tree",
    "learned_urdf",
    "calibration_report",
    "format_report",
    "CalibratedURDF",
    "calibrated_urdf",
    "format_diff",
]
