"""The offline replay loop: learn from a bag's commands and observations exactly as scheme_node would, without ROS.

The bag's ``/joint_commands`` and ``/observations`` are decoded into rclpy messages (:mod:`.bag_io`) and go through
scheme_node's own path (:func:`.message_feed.feed_message` into the pairer, :func:`.message_feed.learn_sample` per
sample, a final ``flush(inf)``), with the settings of its parameter file. The report, plot and command line around it
are ``body_scheme_apps.replay_offline``.
"""

from __future__ import annotations

import bisect
import math
import pathlib
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import rotational_error, translational_error

from . import conversions
from .bag_io import bag_topics, read_messages, session_info
from .message_feed import feed_message, learn_sample
from .settings import SchemeSettings
from .sources import translate

__all__ = ["ReplayResult", "default_params_file", "replay_bag", "COMMANDS", "OBSERVATIONS", "GROUND_TRUTH"]

COMMANDS, OBSERVATIONS, GROUND_TRUTH = "/joint_commands", "/observations", "/ground_truth/marker_poses"


@dataclass
class ReplayResult:
    """What a replay produced.

    Attributes
    ----------
    settings : SchemeSettings
    learner : BodySchemeLearner
        The learner after the last sample.
    steps : list of dict
        One record per learning step: ``step``, ``command_index`` (index of the paired command in the bag),
        ``stamp`` (s), ``phase`` (after the step), ``edges`` (tree edges after the step: parent, child, model,
        trans_error, rot_error, valid, in_mismatch) and ``prediction`` (``{part: (trans m, rot rad)}`` predicted
        before the step, against ground truth; empty without a body scheme or ground truth).
    events : list of Event
    rejected : collections.Counter
        Dropped inputs by reason, from the messages, the pairer and the learner.
    n_commands : int
        Command messages in the bag.
    seconds : float
        Wall time of the learning loop.
    info : dict or None
        The bag's ``/session/info``.
    imported : collections.Counter or None
        With a source map: the recording's poses and samples, and what the import dropped by reason
        (:class:`.sources.Translation`).
    """

    settings: SchemeSettings
    learner: object
    steps: list = field(default_factory=list)
    events: list = field(default_factory=list)
    rejected: Counter = field(default_factory=Counter)
    n_commands: int = 0
    seconds: float = 0.0
    info: dict | None = None
    imported: Counter | None = None


def default_params_file():
    """scheme_node's shipped parameter file: the installed share directory, else the source tree."""
    try:
        installed = pathlib.Path(get_package_share_directory("body_scheme_nodes")) / "config" / "scheme_node.yaml"
        if installed.exists():
            return installed
    except PackageNotFoundError:
        pass
    return pathlib.Path(__file__).resolve().parents[1] / "config" / "scheme_node.yaml"


# ---------------------------------------------------------------------- the replay
def _command_stamps_and_truth(path):
    """Stamps of the commands (increasing, as the pairer keeps them) and the ground truth of each command.

    Returns
    -------
    stamps : list of float
    truth : list of dict of int to ndarray, shape (4, 4), or None
        Per command: the ground-truth poses stamped at or right after it (and before the next command).
    """
    stamps, truth_stamps, truth_poses = [], [], []
    for item in read_messages(path, [COMMANDS, GROUND_TRUTH]):
        stamp = conversions.seconds_from_stamp(item.msg.header.stamp)
        if item.topic == COMMANDS:
            if not stamps or stamp > stamps[-1]:
                stamps.append(stamp)
        else:
            try:
                _, poses, _ = conversions.observations_from_msg(item.msg)
            except InvalidInputError:  # evaluation only: a broken ground-truth message just gives no error
                continue
            truth_stamps.append(stamp)
            truth_poses.append(poses)
    order = np.argsort(truth_stamps, kind="stable")
    truth_stamps = [truth_stamps[i] for i in order]
    truth_poses = [truth_poses[i] for i in order]
    truth = []
    for k, stamp in enumerate(stamps):
        j = bisect.bisect_left(truth_stamps, stamp)
        following = stamps[k + 1] if k + 1 < len(stamps) else math.inf
        truth.append(truth_poses[j] if j < len(truth_stamps) and truth_stamps[j] < following else None)
    return stamps, truth


def _prediction_errors(learner, actions, truth):
    """``{part: (trans m, rot rad)}`` of the current body scheme's prediction against ground truth."""
    if learner.body_scheme is None or not truth:
        return {}
    predicted = learner.predict(actions)
    return {part: (float(translational_error(pose, truth[part])), float(rotational_error(pose, truth[part])))
            for part, pose in predicted.items() if part in truth}


def _edge_records(learner):
    keys = ("parent", "child", "model", "trans_error", "rot_error", "valid", "in_mismatch")
    return [{k: status[k] for k in keys} for status in learner.edge_status()]


def replay_bag(path, settings, progress=None, source_map=None):
    """Learn from a bag's commands and observations as scheme_node would.

    Parameters
    ----------
    path : str or os.PathLike
        Session bag (rosbag2 directory), or with ``source_map`` another stack's bag or a table.
    settings : SchemeSettings
    progress : callable, optional
        Called with the number of command messages read so far.
    source_map : SourceMap, optional
        How another stack's recording becomes commands and observations (:mod:`.sources`); it then has no ground
        truth.

    Returns
    -------
    result : ReplayResult

    Raises
    ------
    BagError
        If the bag is missing, corrupt or has topics of unexpected types.
    InvalidInputError
        If the bag has no commands or observations, or its joints are not the settings' ``joint_names``.
    """
    if source_map is not None:
        translation = translate(path, source_map)
        messages, info = translation.messages, None
        command_stamps = [item.log_time * 1e-9 for item in messages if item.topic == COMMANDS]
        truth = [None] * len(command_stamps)
    else:
        topics = bag_topics(path)
        missing = [t for t in (COMMANDS, OBSERVATIONS) if topics.get(t, (None, 0))[1] == 0]
        if missing:
            raise InvalidInputError(f"bag {path} has no messages on {missing}: nothing to learn from")
        info = session_info(path) if "/session/info" in topics else None
        messages = read_messages(path, [COMMANDS, OBSERVATIONS])
        command_stamps, truth = _command_stamps_and_truth(path)
    names = source_map.joint_names if source_map is not None else (info or {}).get("joint_names")
    if names is not None and not set(settings.joint_names) <= set(names):
        raise InvalidInputError(f"the recording's joints are {list(names)}, the settings' joint_names are "
                                f"{list(settings.joint_names)}: pass the robot's parameter file with --params")
    learner, pairer = settings.new_learner(), settings.new_pairer()
    result = ReplayResult(settings=settings, learner=learner, info=info,
                          imported=translation.counts if source_map is not None else None)

    def learn(samples):
        for stamp, actions, observed in samples:
            k = bisect.bisect_right(command_stamps, stamp) - 1
            prediction = _prediction_errors(learner, actions, truth[k] if k >= 0 else None)
            step = learner.step
            events, rejection = learn_sample(learner, stamp, actions, observed)
            if rejection is not None:  # counted as scheme_node counts it; the learner is unchanged
                result.rejected[rejection[0]] += 1
                continue
            result.events += events
            result.steps.append({"step": step, "command_index": k, "stamp": stamp, "phase": learner.phase,
                                 "edges": _edge_records(learner), "prediction": prediction})

    start = time.perf_counter()
    for item in messages:
        kind = "command" if item.topic == COMMANDS else "observations"
        samples, rejections = feed_message(pairer, kind, item.msg, settings.joint_names, settings.frame_id,
                                           settings.message_limits)
        result.rejected.update(code for code, _ in rejections)
        learn(samples)
        if kind == "command":
            result.n_commands += 1
            if progress is not None:
                progress(result.n_commands)
    learn(pairer.flush(math.inf))
    result.seconds = time.perf_counter() - start
    result.rejected += Counter(pairer.rejected) + Counter(learner.rejected)
    return result


# ---------------------------------------------------------------------- the report
