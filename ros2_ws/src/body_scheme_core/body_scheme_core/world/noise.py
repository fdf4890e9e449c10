"""Observation noise: the paper's marker noise, a camera's (worse along the ray, mirrored orientations now and then),
and noisy, partially missing observations.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..transforms import check_transform, concat, mirror_about_ray
from .robots import default_world2root

__all__ = ["PAPER_SIGMA_TRANS", "PAPER_SIGMA_ROT", "ObservationModel"]


#: The paper's measured marker noise (m) and its rotational threshold / 3 (rad).
PAPER_SIGMA_TRANS = 0.044
PAPER_SIGMA_ROT = math.radians(15.0)


class ObservationModel:
    """Noisy, partially missing marker observations from a fixed camera (the paper's ``Y_i`` given ``X_i``).

    Noise model: the position gets Gaussian noise whose RMS 3D error is ``sigma_trans`` (the paper reports one 3D
    standard deviation, 44 mm): isotropic by default (per-axis standard deviation ``sigma_trans / sqrt(3)``), or
    ``depth_ratio`` times larger along the camera's ray to the marker than across it, as a monocular camera's is
    (per-axis ``s`` laterally and ``depth_ratio s`` in depth, ``s = sigma_trans / sqrt(2 + depth_ratio^2)``). The
    orientation is perturbed by a random rotation ``exp(w)``, ``w ~ N(0, (sigma_rot / sqrt(3))^2 I)`` applied in the
    marker frame, so the RMS rotation angle is ``sigma_rot``; with probability ``flip_rate`` it is then replaced by
    its mirror about the ray (:func:`~body_scheme_core.transforms.mirror_about_ray`), the planar ambiguity a marker
    tracker falls into now and then. Each marker is dropped independently with probability ``1 - visibility``,
    except those in ``always_visible``.

    Parameters
    ----------
    sigma_trans : float
        RMS position error, m.
    sigma_rot : float
        RMS rotation error, rad.
    visibility : float
        Probability in [0, 1] that a marker is observed at a step.
    rng : numpy.random.Generator or int or None
    world2root : array-like, shape (4, 4) or None
        Pose of the robot root in the camera (world) frame; ``None``: :func:`default_world2root`.
    always_visible : iterable of int
        Marker ids never dropped (e.g. the root marker).
    depth_ratio : float
        Per-axis position noise along the ray over that across it (1: isotropic).
    flip_rate : float
        Probability in [0, 1] that an observed orientation is mirrored about the ray.
    """

    def __init__(self, sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT, visibility=1.0, rng=None,
                 world2root=None, always_visible=(), depth_ratio=1.0, flip_rate=0.0):
        for name, value in (("sigma_trans", sigma_trans), ("sigma_rot", sigma_rot)):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be a finite number >= 0, got {value!r}")
        if not (0.0 <= visibility <= 1.0):
            raise InvalidInputError(f"visibility must be in [0, 1], got {visibility!r}")
        if not (math.isfinite(depth_ratio) and depth_ratio > 0):
            raise InvalidInputError(f"depth_ratio must be a finite number > 0, got {depth_ratio!r}")
        if not (0.0 <= flip_rate <= 1.0):
            raise InvalidInputError(f"flip_rate must be in [0, 1], got {flip_rate!r}")
        self.depth_ratio = float(depth_ratio)
        self.flip_rate = float(flip_rate)
        self.sigma_trans = float(sigma_trans)
        self.sigma_rot = float(sigma_rot)
        self.visibility = float(visibility)
        self.rng = np.random.default_rng(rng)
        world2root = default_world2root() if world2root is None else world2root
        self.world2root = check_transform(np.array(world2root, dtype=float), name="world2root")
        self.always_visible = frozenset(int(i) for i in always_visible)

    def observe_array(self, root2marker, marker_ids):
        """Observe a sequence of true poses.

        Parameters
        ----------
        root2marker : array-like, shape (n, k, 4, 4)
            True marker poses in the root frame.
        marker_ids : sequence of int, length k

        Returns
        -------
        observations : list of dict of int to ndarray, shape (4, 4)
            Per step, ``{marker id: noisy world2marker}`` of the visible markers.
        """
        root2marker = check_transform(root2marker, name="root2marker", tolerance=1e-6)
        marker_ids = [int(i) for i in marker_ids]
        if root2marker.ndim != 4 or root2marker.shape[1] != len(marker_ids):
            raise InvalidInputError(
                f"root2marker must have shape (n, {len(marker_ids)}, 4, 4), got {root2marker.shape}")
        n, k = root2marker.shape[:2]
        world2marker = concat(self.world2root, root2marker)
        # Draw every random number for every marker, so the noise of one marker does not depend on the others'
        # visibility settings.
        r = self.depth_ratio
        lateral = self.sigma_trans / math.sqrt(2.0 + r * r)
        d_position = self.rng.normal(scale=lateral, size=(n, k, 3))
        d_rotvec = self.rng.normal(scale=self.sigma_rot / math.sqrt(3.0), size=(n, k, 3))
        visible = self.rng.uniform(size=(n, k)) < self.visibility
        visible[:, [c for c, i in enumerate(marker_ids) if i in self.always_visible]] = True
        if r != 1.0:  # stretch the component along the ray to the marker
            ray = world2marker[..., :3, 3] / np.maximum(
                np.linalg.norm(world2marker[..., :3, 3], axis=-1, keepdims=True), 1e-12)
            d_position += (r - 1.0) * np.sum(d_position * ray, axis=-1, keepdims=True) * ray
        noisy = world2marker.copy()
        noisy[..., :3, 3] += d_position
        noisy[..., :3, :3] = world2marker[..., :3, :3] @ Rotation.from_rotvec(
            d_rotvec.reshape(-1, 3)).as_matrix().reshape(n, k, 3, 3)
        if self.flip_rate > 0.0:
            flipped = self.rng.uniform(size=(n, k)) < self.flip_rate
            noisy[flipped] = mirror_about_ray(noisy[flipped])
        return [{marker_ids[c]: noisy[t, c] for c in range(k) if visible[t, c]} for t in range(n)]

    def observe(self, root2marker):
        """Observe one configuration: ``{id: root2marker (4, 4)}`` -> ``{id: noisy world2marker}`` (visible only)."""
        ids = sorted(root2marker)
        stack = np.stack([np.asarray(root2marker[i], dtype=float) for i in ids])[None] if ids else np.zeros(
            (1, 0, 4, 4))
        return self.observe_array(stack, ids)[0]
