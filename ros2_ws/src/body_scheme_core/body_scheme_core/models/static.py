"""Static local model: a rigid transform between two parts that no action moves (complexity 0).

The paper's lowest complexity layer, ``p(Z_ij)`` without action dependency (two markers on one link), and Sturm's
*rigid* articulation model. Parameters (storage layout, 6 numbers): the child's position ``p`` (3) and orientation
as a rotation vector (3) in the parent frame. A local increment is ``[dp (3), w (3)]`` with ``R -> R exp([w]x)``.

:class:`StaticForm` is the vectorised form used by :class:`~body_scheme_core.models.rigid.RigidJointModel`
and :class:`~body_scheme_core.models.rigid_batch.RigidBatch` (leading dimension: a stack of k models).
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from ..rotations import chordal_mean, rotation_log, rotvec_matrix
from .rigid import RigidJointModel

__all__ = ["StaticModel", "StaticForm"]

class StaticForm:
    """The static form, vectorised over a stack of k models (see :mod:`~body_scheme_core.models.rigid`)."""

    N_PARAMS = 6
    N_STORED = 6
    MIN_SAMPLES = 1
    LINEAR = True
    CLOSED_FORM_CANDIDATE = True

    @staticmethod
    def transforms(params, x):
        """``parent2child`` (k, n, 4, 4) of parameters (k, 6); ``x`` (k, n) only gives n."""
        k, n = x.shape
        Z = np.zeros((k, n, 4, 4))
        Z[:, :, :3, :3] = rotvec_matrix(params[:, 3:6])[:, None]
        Z[:, :, :3, 3] = params[:, None, 0:3]
        Z[:, :, 3, 3] = 1.0
        return Z

    @staticmethod
    def twists(params, x):
        """Twists (k, n, 6, 6) (rows ``[dt, w]``, one column per increment): an increment moves the prediction by
        itself."""
        k, n = x.shape
        return np.broadcast_to(np.eye(6), (k, n, 6, 6)).copy()

    @staticmethod
    def evaluate(params, x, twists=True):
        """``(transforms, twists or None)`` at once."""
        return StaticForm.transforms(params, x), (StaticForm.twists(params, x) if twists else None)

    @staticmethod
    def retract(params, delta):
        """``p + dp``, ``R exp([w]x)``; shapes (k, 6) and (k, 6)."""
        out = np.empty_like(params)
        out[:, 0:3] = params[:, 0:3] + delta[:, 0:3]
        out[:, 3:6] = rotation_log(rotvec_matrix(params[:, 3:6]) @ rotvec_matrix(delta[:, 3:6]))
        return out

    @staticmethod
    def initial(x, Z, S, mask, weights=None):
        """Closed form: weighted mean position (per axis) and chordal mean rotation, (k, 6).

        ``weights`` (k, n, 6): robust weights per residual component (IRLS); default: the mask.
        """
        w = np.repeat(mask[..., None].astype(float), 6, axis=-1) if weights is None else weights
        wt = w[..., 0:3] / S[..., 0:1] ** 2
        wr = w[..., 3:6].mean(axis=-1) / S[..., 1] ** 2
        params = np.zeros((Z.shape[0], 6))
        params[:, 0:3] = (wt * Z[..., :3, 3]).sum(axis=1) / np.maximum(wt.sum(axis=1), 1e-300)
        params[:, 3:6] = rotation_log(chordal_mean(Z[..., :3, :3], wr))
        return params

    @staticmethod
    def compile(params):
        """A fast single-sample predictor ``x -> (4, 4)`` of fixed parameters (q,)."""
        Z = StaticForm.transforms(params[None], np.zeros((1, 1)))[0, 0]
        return lambda x: Z.copy()

    @staticmethod
    def action_derivative(params, x):
        """``dZ/da`` (4, 4): zero."""
        return np.zeros((4, 4))

    @staticmethod
    def validate(params):
        """Stored parameters as they are (any finite 6-vector is a pose)."""
        return params


class StaticModel(RigidJointModel):
    """Constant transform ``parent2child``: robust weighted mean of the observations.

    Parameters
    ----------
    parent, child : int
    actions : tuple
        Must be empty (accepted so that every model class has the same constructor signature).
    sigma_trans, sigma_rot, f_scale : float
        See :class:`~body_scheme_core.models.rigid.RigidJointModel`.
    """

    kind = "static"
    form = StaticForm
    class_rank = 0

    @staticmethod
    def form_for(fit_scale):
        """The static form (there is no scale)."""
        return StaticForm

    def __init__(self, parent, child, actions=(), **hyperparameters):
        # A static model depends on no action by definition; a non-empty tuple is a caller's mistake.
        if tuple(actions):
            raise InvalidInputError(f"a static model depends on no action, got actions {tuple(actions)!r}")
        super().__init__(parent, child, (), **hyperparameters)

    @property
    def parent2child_(self):
        """The fitted transform (4, 4)."""
        self._check_fitted()
        return StaticForm.transforms(self.params_[None], np.zeros((1, 1)))[0, 0]

