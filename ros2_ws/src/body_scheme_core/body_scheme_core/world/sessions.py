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
from ..transforms import concat, relative_transform, rotational_error, translational_error
from .babbling import babble
from .body import Body
from .faults import Fault, protocol_schedule
from .noise import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS, ObservationModel
from .robots import powercube_6dof
from .tree import KinematicTree

__all__ = ["Session", "make_session", "joint_blocked_protocol", "limb_deformed_protocol", "START_STAMP_NS",
           "IMAGE_DELAY_NS", "DEFAULT_PERIOD", "FRAME_ID"]


#: Stamp of the first command: 2023-11-14T22:13:20Z, a fixed epoch so recordings are reproducible.
START_STAMP_NS = 1_700_000_000 * 1_000_000_000
#: Time from a command to the image showing its result (the simulators execute kinematically), ns.
IMAGE_DELAY_NS = 5_000_000
#: Seconds between commands, unless a session says otherwise.
DEFAULT_PERIOD = 0.1
#: Frame of observations and ground truth: the camera optical frame.
FRAME_ID = "camera"


@dataclass
class Session:
    """A babbling session: commands, observations, ground truth and the fault timeline.

    One class for every source: the synthetic world (:func:`make_session`), the pybullet simulator
    (:func:`body_scheme_sim.sessions.record_session`) and recorded bags (:func:`body_scheme_nodes.bag_io.read_session`).

    Attributes
    ----------
    actions : ndarray, shape (n, m)
        Commanded actions.
    executed : ndarray, shape (n, m)
        Joint positions actually reached (they differ from ``actions`` where a joint is blocked).
    observations : list of dict of int to ndarray, shape (4, 4)
        Per step ``{marker id: camera2marker}`` of the observed markers, as perceived.
    true_poses : ndarray, shape (n, n_markers, 4, 4)
        True ``camera2marker`` of every marker, in ``marker_ids`` order (evaluation only).
    marker_ids : tuple of int
    faults : list of (int, str)
        Step at which each fault takes effect (it affects that step and later ones) and its schedule entry
        (``"10:block_joint:5:0.8"``, see :mod:`body_scheme_core.world.faults`).
    tree : KinematicTree or None
        The robot's nominal specification (what an engineered model is built from); ``None`` when read from a bag.
    robot : str
        Robot name or URDF path (simulator sessions).
    joint_names : tuple of str
        Joint of each action, in action order.
    command_stamps, observation_stamps : ndarray of int64, shape (n,) or None
        Stamp of each command and of its observation (the image after the command), ns.
    world2root : ndarray, shape (4, 4) or None
        Camera to robot root transform (synthetic sessions).
    camera : body_scheme_sim.camera.Camera or None
        The simulator's camera.
    images : dict of int to ndarray, shape (H, W, 3), dtype uint8
        Stored camera images by step (RGB).
    perception : str
        ``"noise"`` (true poses plus the noise model) or ``"rendered"`` (camera images through the ArUco tracker).
    seed : int or None
    protocol : str
        ``"none"`` or the protocol that made the fault schedule.
    sigma_trans, sigma_rot, visibility, depth_ratio, flip_rate : float
        Noise-model settings (:class:`~body_scheme_core.world.noise.ObservationModel`).
    frame_id : str
    tracker_rejected : dict of str to int
        Rendered perception: tracker detections that gave no pose, by reason.
    visible_truth : ndarray of bool, shape (n, n_markers) or None
        Markers the camera could geometrically see at each step (simulator; not in bags).
    """

    actions: np.ndarray
    executed: np.ndarray
    observations: list
    true_poses: np.ndarray
    marker_ids: tuple
    faults: list = field(default_factory=list)
    tree: KinematicTree | None = None
    robot: str = ""
    joint_names: tuple = ()
    command_stamps: np.ndarray | None = None
    observation_stamps: np.ndarray | None = None
    world2root: np.ndarray | None = None
    camera: object = None
    images: dict = field(default_factory=dict)
    perception: str = "noise"
    seed: int | None = None
    protocol: str = "none"
    sigma_trans: float = PAPER_SIGMA_TRANS
    sigma_rot: float = PAPER_SIGMA_ROT
    visibility: float = 1.0
    depth_ratio: float = 1.0
    flip_rate: float = 0.0
    frame_id: str = FRAME_ID
    tracker_rejected: dict = field(default_factory=dict)
    visible_truth: np.ndarray | None = None

    @property
    def n_steps(self):
        """Number of time steps (commands)."""
        return self.actions.shape[0]

    @property
    def stamps(self):
        """Command stamps in seconds, shape (n,)."""
        return self.command_stamps * 1e-9

    @property
    def phase(self):
        """Number of faults in effect at each step (0 before the first), shape (n,)."""
        steps = np.sort(np.array([step for step, _ in self.faults], dtype=int))
        return np.searchsorted(steps, np.arange(self.n_steps), side="right")

    @property
    def visible(self):
        """Boolean mask (n, n_markers) of the observed markers."""
        return np.array([[i in obs for i in self.marker_ids] for obs in self.observations], dtype=bool).reshape(
            self.n_steps, len(self.marker_ids))

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

    def observation_errors(self, marker_ids=None):
        """Translational (m) and rotational (rad) errors of every observed pose against ground truth.

        Parameters
        ----------
        marker_ids : iterable of int or None
            Only these markers (``None``: all).

        Returns
        -------
        errors : ndarray, shape (k, 2)
        """
        errors = []
        for k, observed in enumerate(self.observations):
            for marker_id, camera2marker in observed.items():
                if marker_ids is None or marker_id in marker_ids:
                    truth = self.true_poses[k, self._column(marker_id)]
                    errors.append((translational_error(camera2marker, truth), rotational_error(camera2marker, truth)))
        return np.array(errors).reshape(-1, 2)


def make_session(robot, n_steps, seed, faults=(), sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT,
                 visibility=1.0, world2root=None, always_visible=(), above_ground=None, ground_z=0.0, depth_ratio=1.0,
                 flip_rate=0.0, actions=None):
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
    sigma_trans, sigma_rot, visibility, world2root, always_visible, depth_ratio, flip_rate
        See :class:`ObservationModel`.
    above_ground, ground_z
        See :func:`babble`.
    actions : array-like, shape (n_steps, m), optional
        The commands, instead of babbling (e.g. an exploration plan); within the joint limits.

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
    if actions is None:
        A = babble(tree, n_steps, rng_actions, above_ground=above_ground, ground_z=ground_z)
    else:
        A = np.array(actions, dtype=float)
        if A.shape != (n_steps, tree.n_actions) or not np.all(np.isfinite(A)):
            raise InvalidInputError(f"actions must be {n_steps} finite commands of {tree.n_actions} actions, got "
                                    f"shape {A.shape}")
    executed = np.zeros_like(A)
    root2marker = np.zeros((n_steps, len(tree.marker_ids), 4, 4))
    body, start = original, 0
    boundaries = [step for step, _ in faults] + [n_steps]
    for index, end in enumerate(boundaries):
        if end > start:
            executed[start:end] = body.execute(A[start:end])
            root2marker[start:end] = body.true_marker_array(A[start:end])
        if index < len(faults):
            body = faults[index][1].apply(body, original)
            start = end
    observer = ObservationModel(sigma_trans, sigma_rot, visibility, rng_noise, world2root, always_visible,
                                depth_ratio, flip_rate)
    observations = observer.observe_array(root2marker, tree.marker_ids)
    command_stamps = START_STAMP_NS + int(round(DEFAULT_PERIOD * 1e9)) * np.arange(n_steps, dtype=np.int64)
    return Session(tree=tree, actions=A, executed=executed, observations=observations,
                   true_poses=concat(observer.world2root, root2marker), marker_ids=tree.marker_ids,
                   faults=[(step, f"{step}:{fault.entry}") for step, fault in faults],
                   joint_names=tuple(tree.action_joint_names), command_stamps=command_stamps,
                   observation_stamps=command_stamps + IMAGE_DELAY_NS, world2root=observer.world2root,
                   sigma_trans=sigma_trans, sigma_rot=sigma_rot, visibility=visibility, depth_ratio=depth_ratio,
                   flip_rate=flip_rate, seed=seed)


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
