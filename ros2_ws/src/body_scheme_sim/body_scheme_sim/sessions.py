"""Recorded babbling sessions of the simulator: commands, what the camera saw, ground truth and the fault timeline.

:func:`record_session` babbles with a :class:`~body_scheme_sim.world.SimWorld`, applies a fault schedule
(:mod:`body_scheme_core.world.faults`) at the given steps and collects per step the command, the observation and the
ground truth. Perception is either

- ``"noise"``: the visible markers' true poses perturbed with the paper's noise (``SimWorld.observe_noisy``), fast;
- ``"rendered"``: the camera image through the ArUco tracker (:class:`body_scheme_core.perception.MarkerTracker`),
  exactly what ``sim_node`` + ``tracker_node`` produce.

Both give ``{marker id: camera2marker}`` per step, so downstream code cannot tell them apart. The commands are
babbled on the healthy robot before any fault, from their own random stream, so sessions with the same seed share
their commands whatever the faults and the perception mode.

Sessions are the core's :class:`~body_scheme_core.world.Session`. Time: command ``k`` is stamped
``START_STAMP_NS + k * period``; its observation (the camera image taken after the
arm moved) :data:`IMAGE_DELAY_NS` later. Stamps are integer nanoseconds, so bags round-trip them exactly.

:func:`record_protocol` records the paper's two adaptation experiments (Sec. IV-B/C, 4 blocks of 100 samples) on
the 6-DOF arm, with the fault schedules of :func:`body_scheme_core.world.protocol_schedule`.
Bags: :mod:`body_scheme_nodes.bag_io`.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.perception import MarkerTracker, rejection_kind
from body_scheme_core.world import (
    IMAGE_DELAY_NS,
    PAPER_SIGMA_ROT,
    PAPER_SIGMA_TRANS,
    PROTOCOL_FAULTS,
    START_STAMP_NS,
    Session,
    babble,
    parse_fault_schedule,
    protocol_schedule,
)

from .babbling import babbling_screen
from .world import SimWorld

__all__ = [
    "PERCEPTION_MODES",
    "PROTOCOLS",
    "RENDERED_SIGMA_ROT",
    "RENDERED_SIGMA_TRANS",
    "record_session",
    "PROTOCOL_MARKERS_OF_INTEREST",
    "protocol_faults",
    "record_protocol",
]

PERCEPTION_MODES = ("noise", "rendered")
#: The learner's noise sigmas for rendered perception: the tracker's accuracy on the sim's images (median 2-4 mm and
#: 0.3-0.5 deg on the arm's markers, docs/sim.md). 3-sigma validity (30 mm) then rejects local models through a marker
#: whose orientation is often mirrored, and the structure search routes around it (e.g. 1->3 instead of 1->2->3).
RENDERED_SIGMA_TRANS = 0.01
RENDERED_SIGMA_ROT = math.radians(5.0)


def record_session(robot="powercube_6dof", n_steps=400, seed=0, faults=(), perception="noise",
                   sigma_trans=PAPER_SIGMA_TRANS, sigma_rot=PAPER_SIGMA_ROT, visibility=1.0, image_every=0,
                   markers_of_interest=None, period=0.1, protocol="none", camera=None, markers_path=None,
                   progress=None, package_path=()):
    """Babble with the simulator and record what happens.

    Parameters
    ----------
    robot : str or os.PathLike
        Shipped robot name or URDF path (see :class:`SimWorld`).
    n_steps : int
    seed : int or None
        Equal seeds give equal sessions (commands, noise, faults).
    faults : iterable of str
        Fault schedule entries ``"step:kind:args"`` (:mod:`body_scheme_core.world.faults`); a fault at step ``k``
        affects command ``k`` and later ones.
    perception : str
        ``"noise"`` or ``"rendered"`` (see the module docstring).
    sigma_trans, sigma_rot, visibility : float
        Noise mode: 3D RMS translational (m) and rotational (rad) noise, and the probability that a geometrically
        visible marker is observed.
    image_every : int
        Store every ``image_every``-th camera image (steps 0, N, 2N, ...); 0 stores none.
    markers_of_interest : iterable of int or None
        Markers that must be visible in every babbled configuration
        (:func:`~body_scheme_sim.babbling.babbling_screen`).
    period : float
        Seconds between commands.
    protocol : str
        Name recorded with the session (``"none"`` for a hand-made schedule).
    camera : Camera or None
    markers_path : str or os.PathLike or None
    progress : callable or None
        Called with the number of steps done after each step (e.g. a tqdm bar's ``update``-like callback).
    package_path : iterable of str
        Directories searched first for ``package://`` meshes (:class:`SimWorld`).

    Returns
    -------
    session : Session

    Raises
    ------
    InvalidInputError
        For an unknown perception mode, bad sizes, a fault step outside the session, or a bad schedule entry.
    BabblingError
        If too few valid commands turn up (markers of interest rarely visible).
    """
    if perception not in PERCEPTION_MODES:
        raise InvalidInputError(f"perception must be one of {PERCEPTION_MODES}, got {perception!r}")
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
        raise InvalidInputError(f"n_steps must be an integer >= 1, got {n_steps!r}")
    if isinstance(image_every, bool) or not isinstance(image_every, (int, np.integer)) or image_every < 0:
        raise InvalidInputError(f"image_every must be an integer >= 0, got {image_every!r}")
    if not (math.isfinite(period) and period > 0):
        raise InvalidInputError(f"period must be > 0 s, got {period!r}")
    schedule = parse_fault_schedule(list(faults))
    late = [f"{step}:{fault.entry}" for step, fault in schedule if step >= n_steps]
    if late:
        raise InvalidInputError(f"fault entries {late} lie outside the session's steps 0..{n_steps - 1}")
    rng_actions, rng_noise = np.random.default_rng(seed).spawn(2)
    period_ns = int(round(period * 1e9))

    with SimWorld(robot=robot, camera=camera, markers_path=markers_path, seed=seed,
                  package_path=package_path) as world:
        marker_ids = tuple(sorted(world.marker_ids))
        tracker = _tracker(world) if perception == "rendered" else None
        actions = babble(world, n_steps, rng_actions, screen=babbling_screen(world, markers_of_interest))
        executed = np.zeros_like(actions)
        true_poses = np.zeros((n_steps, len(marker_ids), 4, 4))
        visible_truth = np.zeros((n_steps, len(marker_ids)), dtype=bool)
        observations, images, rejected = [], {}, Counter()
        pending = list(schedule)
        for k in range(n_steps):
            while pending and pending[0][0] == k:
                world.apply(pending.pop(0)[1])
            executed[k] = world.execute(actions[k])
            truth = world.true_marker_poses()
            true_poses[k] = [truth[marker_id] for marker_id in marker_ids]
            visible = world.visible_marker_ids()
            visible_truth[k] = [marker_id in visible for marker_id in marker_ids]
            image = world.render() if tracker is not None or (image_every and k % image_every == 0) else None
            if tracker is not None:
                poses, dropped = tracker.detect(image)
                rejected.update(rejection_kind(reason) for _, reason in dropped)
            else:
                poses = world.observe_noisy(sigma_trans, sigma_rot, visibility, rng=rng_noise)
            observations.append(poses)
            if image_every and k % image_every == 0:
                images[k] = image
            if progress is not None:
                progress(k + 1)
        camera = world.camera
        joint_names = tuple(world.action_joint_names)

    command_stamps = START_STAMP_NS + period_ns * np.arange(n_steps, dtype=np.int64)
    return Session(
        robot=str(robot), joint_names=joint_names, marker_ids=marker_ids, command_stamps=command_stamps,
        observation_stamps=command_stamps + IMAGE_DELAY_NS, actions=actions, executed=executed,
        observations=observations, true_poses=true_poses,
        faults=[(step, f"{step}:{fault.entry}") for step, fault in schedule],
        camera=camera, images=images, perception=perception, seed=seed, protocol=protocol,
        sigma_trans=float(sigma_trans), sigma_rot=float(sigma_rot), visibility=float(visibility),
        tracker_rejected=dict(rejected), visible_truth=visible_truth)


def _tracker(world):
    """The ArUco tracker for the world's camera and marker sizes."""
    sizes = {marker_id: world.robot.marker(marker_id).size for marker_id in world.marker_ids}
    return MarkerTracker(world.camera.K, marker_sizes=sizes)


# ---------------------------------------------------------------------- the paper's protocols
#: Markers that must be visible in the protocols' babbled configurations: the paper's X_6 and X_7 (Sec. IV-B).
PROTOCOL_MARKERS_OF_INTEREST = (6, 7)


#: The protocols the simulator records (their fault schedules are the core's, :data:`PROTOCOL_FAULTS`).
PROTOCOLS = tuple(PROTOCOL_FAULTS)


def protocol_faults(protocol, n_per_block=100):
    """Fault schedule entries of a protocol (``"none"`` or a key of :data:`PROTOCOL_FAULTS`), e.g.
    ``["100:block_joint:5:0.8", "200:repair", "300:block_joint:5:0.8"]``."""
    if protocol == "none":
        return []
    if protocol not in PROTOCOL_FAULTS:
        raise InvalidInputError(f"protocol must be one of {['none', *PROTOCOL_FAULTS]}, got {protocol!r}")
    return [f"{step}:{fault.entry}" for step, fault in protocol_schedule(protocol, n_per_block)]


def record_protocol(protocol, seed, n_per_block=100, perception="noise", **options):
    """Record one of the paper's adaptation protocols (Sec. IV-B/C) on the simulated 6-DOF arm.

    The fault schedule is the core's (:func:`~body_scheme_core.world.protocol_schedule`): four blocks of
    ``n_per_block`` steps, normal; faulty (``"joint_blocked"``: end-effector joint blocked at 0.8 rad;
    ``"limb_deformed"``: ``tool_joint`` 0.1 m longer and bent by 45 deg about its parent's x axis); repaired; faulty
    again the same way (so the learner can recall the model of block 2). Commands are babbled such that markers 6
    and 7 are visible on the healthy robot, as in the paper.

    Parameters
    ----------
    protocol : str
    seed : int
    n_per_block : int
    perception : str
    **options
        Further arguments of :func:`record_session`.

    Returns
    -------
    session : Session
    """
    faults = protocol_faults(protocol, n_per_block)
    options.setdefault("markers_of_interest", PROTOCOL_MARKERS_OF_INTEREST)
    return record_session("powercube_6dof", 4 * n_per_block, seed, faults=faults, perception=perception,
                          protocol=protocol, **options)
