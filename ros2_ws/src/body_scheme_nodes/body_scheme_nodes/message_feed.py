"""From decoded messages to learning samples, without ROS: the one path scheme_node and replay_offline share.

scheme_node calls :func:`feed_message` for every message it takes in, ``pairer.flush(now)`` and then
:func:`learn_sample` for each sample; replay_offline does the same over a bag (with a final ``flush(inf)``). Because
both go through these lines with the same messages and settings, an offline replay and a replay through the ROS graph
learn from identical samples.
"""

from __future__ import annotations

from body_scheme_core.errors import ActionOutOfRangeError, InvalidInputError, LearnerStepError, StampOrderError

from . import conversions

__all__ = ["MESSAGE_KINDS", "feed_message", "learn_sample"]

#: Kinds of message scheme_node learns from: a ``sensor_msgs/JointState`` command or a ``MarkerPoses`` observation.
MESSAGE_KINDS = ("command", "observations")


def feed_message(pairer, kind, msg, joint_names):
    """Convert one message and hand it to the pairer.

    Parameters
    ----------
    pairer : body_scheme_core.pairing.CommandObservationPairer
    kind : str
        ``"command"`` (``msg`` is a ``sensor_msgs/JointState``) or ``"observations"`` (``MarkerPoses``).
    msg : object
    joint_names : sequence of str
        Joint names in action-vector order.

    Returns
    -------
    samples : list of (float, ndarray of shape (m,), dict of int to ndarray of shape (4, 4))
        Learning samples ``(observation stamp, actions, observations)`` this message resolved (commands only).
    rejections : list of (str, str)
        Reason code and detail of everything dropped: ``invalid_pose`` / ``repeated_id`` per marker, or
        ``bad_command_message`` / ``bad_observations_message`` for a message that is unusable as a whole.
    """
    if kind not in MESSAGE_KINDS:
        raise ValueError(f"kind must be one of {MESSAGE_KINDS}, got {kind!r}")
    try:
        if kind == "command":
            stamp, actions = conversions.actions_from_joint_state(msg, joint_names)
            return pairer.add_command(stamp, actions), []
        stamp, observations, dropped = conversions.observations_from_msg(msg)
        pairer.add_observation(stamp, observations)
        return [], [(code, f"marker {marker_id}: {detail}") for marker_id, code, detail in dropped]
    except InvalidInputError as error:
        return [], [(f"bad_{kind}_message", str(error))]


def learn_sample(learner, stamp, actions, observations):
    """``learner.update`` on one paired sample, with the learner's refusals as reason codes.

    Returns
    -------
    events : list of SchemeEvent, or None if the sample was refused (the learner is then unchanged)
    rejection : (str, str) or None
        Reason code and detail: ``command_out_of_range``, ``older_than_state`` (a stamp before the learner's last
        step, e.g. a bag replayed into a restored state), ``bad_sample`` or ``learner_error`` (a defect inside the
        learner: the step was undone, the learner goes on).
    """
    try:
        return learner.update(actions, observations, stamp=stamp), None
    except ActionOutOfRangeError as error:
        return None, ("command_out_of_range", str(error))
    except StampOrderError as error:
        return None, ("older_than_state", str(error))
    except InvalidInputError as error:
        return None, ("bad_sample", str(error))
    except LearnerStepError as error:
        return None, ("learner_error", str(error))
