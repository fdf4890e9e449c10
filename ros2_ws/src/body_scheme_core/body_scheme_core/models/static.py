"""Static local model: a rigid transform between two parts that no action moves (complexity 0).

This is the learned model of the paper's lowest complexity layer, ``p(Z_ij)`` without action dependency, e.g. two
markers on the same link. It fits the chordal mean of the observed relative transforms.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError, ModelFileError
from ..transforms import check_transform, project_to_rotation, rotational_error, translational_error
from .base import LocalModel, check_actions, check_observations

__all__ = ["StaticModel"]


class StaticModel(LocalModel):
    """Constant transform ``parent2child``, the chordal mean of the training observations.

    Parameters
    ----------
    parent, child : int
        Part ids; the model predicts ``parent2child``.

    Attributes
    ----------
    parent2child_ : ndarray, shape (4, 4)
        Mean translation and the rotation nearest (Frobenius) to the mean rotation matrix.
    std_ : ndarray, shape (2,)
        Per-axis sample standard deviation of the training observations around the mean: translational (m) and
        rotational (rad), i.e. ``sqrt(sum(err^2) / (3 (n - 1)))`` with ``err`` the distances and angles; 0 if
        ``n < 2``. Unlike the GP's latent std this is the spread of the observations, noise included.
    n_samples_ : int
        Number of training samples.
    """

    kind = "static"

    def __init__(self, parent, child, actions=()):
        super().__init__(parent, child, ())
        # A static model depends on no action by definition; accepting the argument keeps the constructor
        # signature uniform across model classes, but a non-empty tuple is a caller's mistake.
        if tuple(actions):
            raise InvalidInputError(f"a static model depends on no action, got actions {tuple(actions)!r}")

    @property
    def is_fitted(self):
        return hasattr(self, "parent2child_")

    def fit(self, A, Z):
        """Fit the chordal mean of ``Z``.

        Parameters
        ----------
        A : array-like, shape (n, m)
            Full action vectors (ignored apart from validation).
        Z : array-like, shape (n, 4, 4)
            Observed relative transforms ``parent2child``.

        Returns
        -------
        self : StaticModel
        """
        _, Z = check_observations(A, Z)
        mean = np.eye(4)
        mean[:3, :3] = project_to_rotation(Z[:, :3, :3].mean(axis=0))
        mean[:3, 3] = Z[:, :3, 3].mean(axis=0)
        n = Z.shape[0]
        std = np.zeros(2)
        if n >= 2:
            # Per-axis std, the convention of every (k, 2) std in the package (isotropic Gaussian per axis).
            std[0] = np.sqrt(np.sum(translational_error(Z, mean) ** 2) / (3.0 * (n - 1)))
            std[1] = np.sqrt(np.sum(rotational_error(Z, mean) ** 2) / (3.0 * (n - 1)))
        self.parent2child_ = mean
        self.std_ = std
        self.n_samples_ = n
        return self

    def predict(self, A, return_std=False):
        """Predict the fitted transform for every row of ``A``.

        Parameters
        ----------
        A : array-like, shape (k, m) or (m,)
        return_std : bool

        Returns
        -------
        Z : ndarray, shape (k, 4, 4)
        std : ndarray, shape (k, 2)
            Only if ``return_std``: ``std_`` repeated.
        """
        self._check_fitted()
        A = check_actions(A)
        k = A.shape[0]
        Z = np.broadcast_to(self.parent2child_, (k, 4, 4)).copy()
        if return_std:
            return Z, np.broadcast_to(self.std_, (k, 2)).copy()
        return Z

    def jacobian(self, a, eps=None):
        """Zero derivative ``(m, 4, 4)``: no action moves a static transform."""
        a = check_actions(a)[0]
        return np.zeros((a.shape[0], 4, 4))

    def to_dict(self):
        data = {"kind": self.kind, "parent": self.parent, "child": self.child, "actions": []}
        if self.is_fitted:
            data["parent2child"] = self.parent2child_.tolist()
            data["std"] = self.std_.tolist()
            data["n_samples"] = int(self.n_samples_)
        return data

    @classmethod
    def from_dict(cls, data):
        try:
            if data["kind"] != cls.kind:
                raise ModelFileError(f"expected kind {cls.kind!r}, got {data['kind']!r}")
            if list(data.get("actions", [])):
                raise ModelFileError(f"a static model has no actions, got {data['actions']!r}")
            model = cls(data["parent"], data["child"])
            if "parent2child" in data:
                parent2child = check_transform(data["parent2child"], name="parent2child", tolerance=1e-6)
                std = np.asarray(data["std"], dtype=float)
                if parent2child.shape != (4, 4) or std.shape != (2,) or not np.all(np.isfinite(std)) or np.any(
                        std < 0):
                    raise ModelFileError(f"bad static model state: std {std.tolist()}")
                model.parent2child_ = parent2child
                model.std_ = std
                model.n_samples_ = int(data["n_samples"])
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"cannot read static model from {sorted(data) if isinstance(data, dict) else data!r}: "
                                 f"{exc}") from exc
        return model

