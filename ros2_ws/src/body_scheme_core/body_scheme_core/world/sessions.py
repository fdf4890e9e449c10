"""Babbling sessions: commands, noisy observations, ground truth and the fault timeline, and the paper's protocols.

The commands are babbled on the nominal robot and the noise comes from a separate random stream, so sessions with the
same seed and different faults share actions and noise draws. Every random quantity comes from a
``numpy.random.Generator``, so ``make_session(..., seed=s)`` is reproducible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidInputError
from ..transforms import concat, relative_transform
from .babbling import babble
from .body import Body
from .faults import Fault, protocol_schedule
from .noise import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS, ObservationModel
from .robots import powercube_6dof
from .tree import KinematicTree

__all__ = ["Session", "make_session", "joint_blocked_protocol", "limb_deformed_protocol"]


@dataclass
class Session:
    """A babbling session: commands, noisy observations, ground truth and the fault timeline.

    Attributes
    ----------
    tree : KinematicTree
        The robot's nominal specification (what an engineered model is built from).
    actions : ndarray, shape (n, m)
        Commanded actions.
    executed : ndarray, shape (n, m)
        Joint positions actually reached (differs from ``actions`` where a joint is blocked).
    observations : list of dict of int to ndarray, shape (4, 4)
        Per step ``{marker id: noisy world2marker}`` of the visible markers.
    true_poses : ndarray, shape (n, n_markers, 4, 4)
        True ``world2marker``, markers in ``marker_ids`` order.
    marker_ids : tuple of int
    world2root : ndarray, shape (4, 4)
        Camera (world) to robot root transform.
    faults : list of (int, Fault)
        Step at which each fault takes effect (it affects that step and later ones).
    phase : ndarray, shape (n,)
        Number of faults in effect so far at each step (0 before the first).
    sigma_trans, sigma_rot, visibility : float
        Observation model settings.
    seed : int or None
    """

    tree: KinematicTree
    actions: np.ndarray
    executed: np.ndarray
    observations: list
    true_poses: np.ndarray
    marker_ids: tuple
    world2root: np.ndarray
    faults: list = field(default_factory=list)
    phase: np.ndarray = None
    sigma_trans: float = PAPER_SIGMA_TRANS
    sigma_rot: float = PAPER_SIGMA_ROT
    visibility: float = 1.0
    seed: int | None = None

    @property
    def n_steps(self):
        """Number of time steps."""
        return self.actions.shape[0]

    @property
    def timeline(self):
        """``[(step, description), ...]`` of the faults."""
        return [(step, fault.describe()) for step, fault in self.faults]

    @property
    def visible(self):
        """Boolean mask (n, n_markers) of the observed markers."""
        return np.array([[i in obs for i in self.marker_ids] for obs in self.observations], dtype=bool)

    def _column(self, marker_id):
        try:
            return self.marker_ids.index(int(marker_id))
        except ValueError:
            raise InvalidInputError(f"unknown marker id {marker_id!r}; markers: {list(self.marker_ids)}") from None

    def true_relative(self, id_i, id_j):
        """True ``marker_i2marker_j`` at every step, shape (n, 4, 4)."""
        return relative_transform(self.true_poses[:, self._column(id_i)], self.true_poses[:, self._column(id_j)])

    def relative_observations(self, id_i, id_j):
        """Observed ``Z_ij = Y_i^-1 Y_j`` at the steps where both markers are visible.

        Returns
        -------
        steps : ndarray of int, shape (k,)
        Z : ndarray, shape (k, 4, 4)
        """
        for marker_id in (id_i, id_j):
            self._column(marker_id)
        steps = [t for t, obs in enumerate(self.observations) if id_i in obs and id_j in obs]
        if not steps:
            return np.zeros(0, dtype=int), np.zeros((0, 4, 4))
        Z = relative_transform(np.stack([self.observations[t][id_i] for t in steps]),
                               np.stack([self.observations[t][id_j] for t in steps]))
        return np.array(steps), Z


def make_session(robot, n_steps, seed, faults=(), sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT,
                 visibility=1.0, world2root=None, always_visible=(), above_ground=None, ground_z=0.0):
    """Simulate motor babbling with noisy observations and faults.

    The commands are babbled on the nominal robot and the noise comes from a separate random stream, so sessions
    with the same seed and different faults share actions and noise draws: only the ground truth differs.

    Parameters
    ----------
    robot : KinematicTree or Body
        The robot before any fault.
    n_steps : int
    seed : int or None
        Seed of ``np.random.default_rng``; equal seeds give identical sessions.
    faults : iterable of (int, Fault)
        Fault taking effect at each step, applied in step order to the body of the previous phase.
    sigma_trans, sigma_rot, visibility, world2root, always_visible
        See :class:`ObservationModel`.
    above_ground, ground_z
        See :func:`babble`.

    Returns
    -------
    session : Session
    """
    original = Body.wrap(robot)
    tree = original.tree
    faults = sorted(((int(step), fault) for step, fault in faults), key=lambda item: item[0])
    for step, fault in faults:
        if not isinstance(fault, Fault):
            raise InvalidInputError(f"faults must be (step, Fault) pairs, got {fault!r}")
        if not (0 <= step < n_steps):
            raise InvalidInputError(f"fault step {step} is outside the session's 0..{n_steps - 1}")
    rng_actions, rng_noise = np.random.default_rng(seed).spawn(2)
    A = babble(tree, n_steps, rng_actions, above_ground=above_ground, ground_z=ground_z)
    executed = np.zeros_like(A)
    root2marker = np.zeros((n_steps, len(tree.marker_ids), 4, 4))
    phase = np.zeros(n_steps, dtype=int)
    body, start = original, 0
    boundaries = [step for step, _ in faults] + [n_steps]
    for index, end in enumerate(boundaries):
        if end > start:
            executed[start:end] = body.execute(A[start:end])
            root2marker[start:end] = body.true_marker_array(A[start:end])
            phase[start:end] = index
        if index < len(faults):
            body = faults[index][1].apply(body, original)
            start = end
    observer = ObservationModel(sigma_trans, sigma_rot, visibility, rng_noise, world2root, always_visible)
    observations = observer.observe_array(root2marker, tree.marker_ids)
    return Session(tree=tree, actions=A, executed=executed, observations=observations,
                   true_poses=concat(observer.world2root, root2marker), marker_ids=tree.marker_ids,
                   world2root=observer.world2root, faults=faults, phase=phase, sigma_trans=sigma_trans,
                   sigma_rot=sigma_rot, visibility=visibility, seed=seed)



def joint_blocked_protocol(seed, n_per_block=100, blocked_angle=0.8, sigma_trans=PAPER_SIGMA_TRANS,
                           sigma_rot=PAPER_SIGMA_ROT, visibility=0.919):
    """The paper's "joint stuck" scenario (Sec. IV-B) on :func:`powercube_6dof`.

    Four blocks of ``n_per_block`` steps: normal, end-effector joint (action 5) blocked at ``blocked_angle``,
    repaired, blocked again at the same angle. Commands keep all markers above the table.

    Returns
    -------
    session : Session
    """
    fault = Fault("block_joint", action_index=5, angle=blocked_angle)
    return make_session(powercube_6dof(), 4 * n_per_block, seed,
                        faults=protocol_schedule("joint_blocked", n_per_block, fault), sigma_trans=sigma_trans,
                        sigma_rot=sigma_rot, visibility=visibility, above_ground=True)


def limb_deformed_protocol(seed, n_per_block=100, delta_length=0.1, delta_rotvec=(math.pi / 4, 0.0, 0.0),
                           sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT, visibility=0.79):
    """The paper's "deformed limb" scenario (Sec. IV-C) on :func:`powercube_6dof`.

    Four blocks of ``n_per_block`` steps: normal, tool displaced (``tool_joint`` lengthened by ``delta_length``
    and bent by ``delta_rotvec`` about the wrist), restored, displaced again the same way.

    Returns
    -------
    session : Session
    """
    fault = Fault("deform_limb", joint_or_link="tool_joint", delta_length=delta_length,
                  delta_rotvec=tuple(float(v) for v in delta_rotvec))
    return make_session(powercube_6dof(), 4 * n_per_block, seed,
                        faults=protocol_schedule("limb_deformed", n_per_block, fault), sigma_trans=sigma_trans,
                        sigma_rot=sigma_rot, visibility=visibility, above_ground=True)
