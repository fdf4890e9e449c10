"""From decoded messages to learning samples, without ROS: the one path scheme_node and replay_offline share.

scheme_node calls :func:`feed_message` for every message it takes in, ``pairer.flush(now)`` and then
:func:`learn_sample` for each sample; replay_offline does the same over a bag (with a final ``flush(inf)``). Because
both go through these lines with the same messages and settings, an offline replay and a replay through the ROS graph
learn from identical samples.
"""

from __future__ import annotations

from typing import NamedTuple

from body_scheme_core.errors import ActionOutOfRangeError, InvalidInputError, LearnerStepError, StampOrderError

from . import conversions

__all__ = ["MESSAGE_KINDS", "MessageLimits", "DEFAULT_LIMITS", "Observed", "feed_message", "learn_sample"]

#: Kinds of message scheme_node learns from: a ``sensor_msgs/JointState`` command or a ``MarkerPoses`` observation.
MESSAGE_KINDS = ("command", "observations")


class MessageLimits(NamedTuple):
    """The largest message scheme_node works on; a larger one is refused whole (``oversized_message``) before any
    conversion. ``max_bytes`` is checked on the serialized message, before it is even deserialized
    (:class:`~body_scheme_nodes.intake.BatchIntake`); the counts here, on the deserialized one."""

    max_bytes: int = 1 << 20
    max_joint_names: int = 1000
    max_markers: int = 1000


#: The defaults of scheme_node's ``max_message_bytes``, ``max_joint_names`` and ``max_markers``.
DEFAULT_LIMITS = MessageLimits()


class Observed(NamedTuple):
    """What one ``MarkerPoses`` message observed: the poses ``{id: frame2marker}`` and the covariances it gave them
    ``{id: (6, 6)}`` (:func:`~body_scheme_nodes.conversions.covariances_from_msg`)."""

    poses: dict
    covariances: dict


def _oversize_problem(kind, msg, limits):
    """Why a deserialized message is too large for ``limits`` (more joint names or markers), or None; O(1)."""
    if kind == "command":
        count = max(len(msg.name), len(msg.position))
        if count > limits.max_joint_names:
            return f"JointState with {count} joints (at most {limits.max_joint_names}; max_joint_names)"
    else:
        count = max(len(msg.marker_ids), len(msg.poses))
        if count > limits.max_markers:
            return f"MarkerPoses with {count} markers (at most {limits.max_markers}; max_markers)"
    return None


def feed_message(pairer, kind, msg, joint_names, frame_id="", limits=DEFAULT_LIMITS):
    """Check one message's size and frame, convert it and hand it to the pairer.

    Parameters
    ----------
    pairer : body_scheme_core.pairing.CommandObservationPairer
    kind : str
        ``"command"`` (``msg`` is a ``sensor_msgs/JointState``) or ``"observations"`` (``MarkerPoses``).
    msg : object
    joint_names : sequence of str
        Joint names in action-vector order.
    frame_id : str
        The camera frame: observations in another frame are refused (``wrong_frame``); an observation with an empty
        ``frame_id`` is taken to be in it. ``""`` accepts every frame.
    limits : MessageLimits

    Returns
    -------
    samples : list of (float, ndarray of shape (m,), Observed)
        Learning samples ``(observation stamp, actions, observed)`` this message resolved (commands only).
    rejections : list of (str, str)
        Reason code and detail of everything dropped: ``invalid_pose`` / ``repeated_id`` per marker, or
        ``bad_command_message`` / ``bad_observations_message`` for a message that is unusable as a whole,
        ``oversized_message`` (more names or markers than ``limits`` allow) or ``wrong_frame``.
    """
    if kind not in MESSAGE_KINDS:
        raise ValueError(f"kind must be one of {MESSAGE_KINDS}, got {kind!r}")
    problem = _oversize_problem(kind, msg, limits)
    if problem is not None:
        return [], [("oversized_message", problem)]
    if kind == "observations" and frame_id and msg.header.frame_id and msg.header.frame_id != frame_id:
        return [], [("wrong_frame", f"MarkerPoses in frame {msg.header.frame_id[:100]!r}, not the camera frame "
                                    f"{frame_id!r}")]
    try:
        if kind == "command":
            stamp, actions = conversions.actions_from_joint_state(msg, joint_names)
            return pairer.add_command(stamp, actions), []
        stamp, observations, dropped = conversions.observations_from_msg(msg)
        pairer.add_observation(stamp, Observed(observations, conversions.covariances_from_msg(msg, observations)))
        return [], [(code, f"marker {marker_id}: {detail}") for marker_id, code, detail in dropped]
    except InvalidInputError as error:
        return [], [(f"bad_{kind}_message", str(error))]


def learn_sample(learner, stamp, actions, observed):
    """``learner.update`` on one paired sample (``observed``: :class:`Observed`), with the learner's refusals as reason
    codes.

    Returns
    -------
    events : list of SchemeEvent, or None if the sample was refused (the learner is then unchanged)
    rejection : (str, str) or None
        Reason code and detail: ``command_out_of_range``, ``older_than_state`` (a stamp before the learner's last
        step, e.g. a bag replayed into a restored state), ``bad_sample`` or ``learner_error`` (a defect inside the
        learner: the step was undone, the learner goes on).
    """
    try:
        return learner.update(actions, observed.poses, stamp=stamp, covariances=observed.covariances), None
    except ActionOutOfRangeError as error:
        return None, ("command_out_of_range", str(error))
    except StampOrderError as error:
        return None, ("older_than_state", str(error))
    except InvalidInputError as error:
        return None, ("bad_sample", str(error))
    except LearnerStepError as error:
        return None, ("learner_error", str(error))
