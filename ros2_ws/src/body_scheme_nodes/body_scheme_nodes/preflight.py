"""Pre-flight: what must hold before babbling moves a real arm, and one line naming each thing that does not.

babble_node collects the facts (:class:`PreflightFacts`) from its subscriptions and sends nothing while
:func:`preflight_failures` returns any line. A check can be skipped on purpose (``preflight_skip``), e.g. ``markers``
for a first session whose markers are not placed yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["CHECKS", "PreflightFacts", "preflight_failures", "unseen_markers"]

#: The checks, in the order they are reported.
CHECKS = ("joint_states", "controller", "camera", "camera_info", "markers")


@dataclass
class PreflightFacts:
    """What babble_node knows when it is about to start.

    Attributes
    ----------
    joint_state_age : float or None
        s since the last usable joint state (None: none yet).
    joint_state_problem : str
        Why the last joint state was refused ("" if none was).
    joint_states_topic, controller_topic, camera_topic, camera_info_topic : str
        The topics, for the messages.
    controller_subscribers : int
        Subscribers of the controller's trajectory topic (the controller is loaded and active).
    camera_age : float or None
        s since the last observations message.
    camera_info : bool
        A ``sensor_msgs/CameraInfo`` arrived.
    seen_markers : set of int
        Markers observed since the arm reported its start posture.
    expected_markers : tuple of int
        The robot's markers: at least one of them must be seen there (empty: any marker). The others need not be:
        a planned marker faces the camera in some postures only, often not in the start posture.
    """

    joint_state_age: float | None = None
    joint_state_problem: str = ""
    joint_states_topic: str = "/joint_states"
    controller_subscribers: int = 0
    controller_topic: str = ""
    camera_age: float | None = None
    camera_topic: str = ""
    camera_info: bool = False
    camera_info_topic: str = ""
    seen_markers: set = field(default_factory=set)
    expected_markers: tuple = ()


def preflight_failures(facts, fresh=3.0, skip=()):
    """``[(check, one-line reason)]`` of every check that fails, in :data:`CHECKS` order (empty: all pass).

    ``fresh``: s within which joint states and camera messages must have arrived.
    """
    failures = []

    def fail(check, reason):
        if check not in skip:
            failures.append((check, f"{check}: {reason}"))

    if facts.joint_state_age is None or facts.joint_state_age > fresh:
        refused = f" (the last was refused: {facts.joint_state_problem})" if facts.joint_state_problem else ""
        when = "none yet" if facts.joint_state_age is None else \
            f"the last usable one is {facts.joint_state_age:.1f} s old"
        fail("joint_states", f"no fresh joint state naming the configured joints on {facts.joint_states_topic}: "
                             f"{when}{refused}")
    if facts.controller_subscribers == 0:
        fail("controller", f"nothing subscribes to {facts.controller_topic}: is the joint_trajectory_controller "
                           f"loaded and active?")
    if facts.camera_age is None or facts.camera_age > fresh:
        when = "none yet" if facts.camera_age is None else f"the last is {facts.camera_age:.1f} s old"
        fail("camera", f"no fresh observations on {facts.camera_topic} (the tracker's output): {when}")
    if not facts.camera_info:
        fail("camera_info", f"no sensor_msgs/CameraInfo on {facts.camera_info_topic}: the camera is not calibrated "
                            f"or not running")
    expected = set(facts.expected_markers)
    if not (facts.seen_markers & expected if expected else facts.seen_markers):
        wanted = f"none of {sorted(expected)}" if expected else "no marker"
        fail("markers", f"{wanted} seen at the start posture" + (
            f" (seen: {sorted(facts.seen_markers)})" if facts.seen_markers else " (none seen)"))
    return failures


def unseen_markers(facts):
    """The expected markers not seen at the start posture (named when the pre-flight passes)."""
    return sorted(set(facts.expected_markers) - facts.seen_markers)
