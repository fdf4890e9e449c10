"""Local model classes p(Z_ij | A_ij), one module each, and the registry used by persistence.

Rigid joints (:class:`StaticModel`, :class:`PrismaticModel`, :class:`RevoluteModel` on the shared
:class:`RigidJointModel`), chains of joints between two observed parts (:class:`ChainModel`), Gaussian processes
(:class:`GPModel`; kernel and hyperparameters in :mod:`.gp_kernel`), the robot's specification
(:class:`EngineeredModel`), and the two batches that let hundreds of candidates learn at once (:class:`GPBatch`,
:class:`RigidBatch`).
"""

from __future__ import annotations

from ..errors import ModelFileError
from .base import LocalModel, check_action_batch, check_observations
from .chain import ChainModel, chain_form
from .chain_spec import chain_from_engineered, increment_jacobian
from .engineered import EngineeredModel, engineered_models
from .gp import GPModel
from .gp_batch import GPBatch
from .gp_kernel import (
    DEFAULT_LENGTH_SCALE,
    DEFAULT_SIGMA_ROT,
    DEFAULT_SIGMA_TRANS,
    DEFAULT_SIGNAL_STD_ROT,
    DEFAULT_SIGNAL_STD_TRANS,
    GPHyperparameters,
    squared_exponential,
)
from .prismatic import PrismaticModel
from .revolute import RevoluteModel
from .rigid import RigidJointModel
from .rigid_batch import RIGID_CLASSES, RigidBatch
from .rigid_fit import DEFAULT_F_SCALE, huber_weights, pose_residuals, robust_cost
from .static import StaticModel

__all__ = [
    "LocalModel",
    "check_action_batch",
    "check_observations",
    "StaticModel",
    "PrismaticModel",
    "RevoluteModel",
    "RigidJointModel",
    "ChainModel",
    "chain_form",
    "chain_from_engineered",
    "increment_jacobian",
    "RigidBatch",
    "RIGID_CLASSES",
    "DEFAULT_F_SCALE",
    "huber_weights",
    "pose_residuals",
    "robust_cost",
    "EngineeredModel",
    "engineered_models",
    "GPModel",
    "GPBatch",
    "GPHyperparameters",
    "squared_exponential",
    "DEFAULT_LENGTH_SCALE",
    "DEFAULT_SIGMA_ROT",
    "DEFAULT_SIGMA_TRANS",
    "DEFAULT_SIGNAL_STD_ROT",
    "DEFAULT_SIGNAL_STD_TRANS",
    "MODEL_CLASSES",
    "model_from_dict",
]

#: Local model classes by their ``kind``, the key written into saved files.
MODEL_CLASSES: dict[str, type[LocalModel]] = {
    cls.kind: cls for cls in (StaticModel, PrismaticModel, RevoluteModel, ChainModel, EngineeredModel, GPModel)}


def model_from_dict(data):
    """Rebuild a local model from its :meth:`LocalModel.to_dict` output, dispatching on ``data["kind"]``.

    Raises
    ------
    ModelFileError
        If ``data`` is not a dict, has no ``kind``, or names an unknown kind.
    """
    if not isinstance(data, dict):
        raise ModelFileError(f"a local model must be stored as a dict, got {type(data).__name__}")
    if "kind" not in data:
        raise ModelFileError(f"local model dict has no 'kind'; keys: {sorted(data)}")
    kind = data["kind"]
    cls = MODEL_CLASSES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ModelFileError(f"unknown local model kind {kind!r}; known: {sorted(MODEL_CLASSES)}")
    return cls.from_dict(data)
