"""babble_node's parameters (in-process; driving an arm over DDS is in tests/test_system_babble_node.py)."""

from __future__ import annotations

import contextlib
import pathlib
import time

import numpy as np
import pybullet_data
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from body_scheme_core.errors import InvalidInputError
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes.babble_node import BabbleNode, watched_status
from body_scheme_nodes.preflight import unseen_markers

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config" / "babble_node.yaml"
BUILT_IN = {"use_sim_time", "start_type_description_service"}
#: In-process tests without a controller or camera: skip those pre-flight checks on purpose.
NO_INPUTS_BUT_JOINT_STATES = Parameter("preflight_skip", value=["controller", "camera", "camera_info", "markers"])


@contextlib.contextmanager
def babble_node(overrides=()):
    """A BabbleNode with ``overrides`` in a fresh rclpy context."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = BabbleNode(context=context, parameter_overrides=list(overrides))
        try:
            yield node
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def declared_parameters(overrides=()):
    """The parameters of a BabbleNode with ``overrides``, and its joint names."""
    with babble_node(overrides) as node:
        names = [n for n in node.list_parameters([], 10).names if n not in BUILT_IN]
        return {p.name: p.value for p in node.get_parameters(names)}, node.driver.joint_names


def test_yaml_holds_every_parameter_at_its_declared_default():
    """config/babble_node.yaml lists exactly the declared parameters, each at its default and of its type."""
    declared, joint_names = declared_parameters()
    in_yaml = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert set(in_yaml) == set(declared)
    for name, value in in_yaml.items():
        default = declared[name] if declared[name] is not None else []
        assert value == (list(default) if isinstance(default, (list, tuple)) else default), name
        assert type(value) is type(list(default) if isinstance(default, (list, tuple)) else default), name
    assert joint_names == ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6")


@pytest.mark.slow
def test_the_driver_refuses_goals_past_the_margin_in_collision_or_outside_the_box():
    """Joint limits less the margin, the workspace box (every link origin under 0.9 m: the upright arm is not) and
    the collision screen (a 7-joint arm from pybullet_data, with its meshes) each refuse a goal, by name; a goal that
    passes all three is fine."""
    box = Parameter("workspace", value=[-2.0, -2.0, -0.01, 2.0, 2.0, 0.9])
    with babble_node([box, Parameter("limit_margin", value=0.1)]) as node:
        driver = node.driver
        safety, zero = driver.safety, np.zeros(6)
        assert np.allclose(safety.upper, [1.4, 1.1, 1.4, 1.4, 1.4, 1.4])
        assert driver.refusal([1.45, 0.5, 0.5, 0, 0, 0], start=zero) == "joint limit"
        assert driver.refusal(zero, start=zero) == "workspace"
        goals = np.random.default_rng(0).uniform(safety.lower, safety.upper, size=(200, 6))
        assert {driver.refusal(goal, start=zero) for goal in goals} == {None, "workspace"}
        leaning, other_way = np.array([0, 1.0, 0, 0, 0, 0]), np.array([0, -1.0, 0, 0, 0, 0])
        assert driver.refusal(leaning, start=leaning) is None and driver.refusal(other_way, start=other_way) is None
        assert driver.refusal(other_way, start=leaning) == "workspace"  # on the way it stands upright
    kuka = str(pathlib.Path(pybullet_data.getDataPath()) / "kuka_iiwa" / "model.urdf")
    with babble_node([Parameter("robot", value=kuka)]) as node:  # +-170 deg: it can hit itself and the ground
        safety, zero = node.driver.safety, np.zeros(7)
        goals = np.random.default_rng(0).uniform(safety.lower, safety.upper, size=(100, 7))
        assert {node.driver.refusal(goal, start=zero) for goal in goals} == {None, "collision"}


def test_a_box_that_leaves_out_the_base_is_refused_at_start_and_a_refusal_names_the_link():
    """docs/your-robot.md's first example box started above the base link's origin (z 0), so every command was refused
    and the log only said the camera was quiet. Now the node will not start and names the link; a draw that leaves
    the box names the links outside it."""
    with pytest.raises(InvalidInputError, match="does not hold link 'base' at .* whose origin no joint moves"):
        with babble_node([Parameter("workspace", value=[-0.8, -0.8, 0.05, 0.8, 0.8, 1.2])]):
            pass
    with babble_node([Parameter("workspace", value=[-2.0, -2.0, -0.01, 2.0, 2.0, 0.9])]) as node:
        upright = node.driver.workspace_problem(np.zeros(6))
        assert upright and all(part.split(" at ")[0] in node.driver.tree.link_poses(np.zeros(6))
                               for part in upright.split("; "))
        assert node.driver.workspace_problem([0, 1.0, 0, 0, 0, 0]) == ""
    # Links that joints this node does not command move (joint2 tilts link4 out of the way) are not "fixed".
    with babble_node([Parameter("joint_names", value=["joint4", "joint5", "joint6"]),
                      Parameter("workspace", value=[-2.0, -2.0, -0.01, 2.0, 2.0, 0.69])]) as node:
        assert node.driver.joint_names == ("joint4", "joint5", "joint6")


def test_a_subset_of_joints_is_commanded_and_the_others_are_held_as_reported():
    """joint_names: only those joints are limited and sent; the safety checks put the others where the last joint
    state says (zero before), so a goal is refused when the other joints make it leave the box."""
    box = Parameter("workspace", value=[-2.0, -2.0, -0.01, 2.0, 2.0, 0.9])
    with babble_node([Parameter("joint_names", value=["joint3", "joint2"]), box]) as node:
        driver = node.driver
        assert driver.joint_names == ("joint3", "joint2") and driver.safety.lower.shape == (2,)
        assert np.allclose(driver.posture([0.5, 0.7]), [0, 0.7, 0.5, 0, 0, 0])
        leaning = [0.0, 1.0]
        assert driver.refusal(leaning, start=leaning) is None
        driver._on_joint_states(JointState(name=["joint1", "joint2", "joint3", "joint4"],
                                           position=[0.3, 0.2, 0.1, float("nan")]))
        assert np.allclose(driver.posture([0.5, 0.7]), [0.3, 0.7, 0.5, 0, 0, 0])  # the NaN is not taken
        assert np.allclose(driver.positions, [0.1, 0.2])
    with pytest.raises(InvalidInputError, match="joint_names"):
        declared_parameters([Parameter("joint_names", value=["joint1", "gripper"])])


def test_the_collision_screen_will_not_start_without_the_meshes(tmp_path):
    """A URDF whose meshes are not found: the screen would pass collisions, so the node refuses to start and says
    what to do."""
    kuka = pathlib.Path(pybullet_data.getDataPath()) / "kuka_iiwa" / "model.urdf"
    copy = tmp_path / "model.urdf"
    copy.write_bytes(kuka.read_bytes())
    with pytest.raises(InvalidInputError, match="collision screen needs the robot's meshes.*collision_check"):
        declared_parameters([Parameter("robot", value=str(copy))])
    params, _ = declared_parameters([Parameter("robot", value=str(copy)), Parameter("collision_check", value=False)])
    assert params["collision_check"] is False


def test_resume_before_the_first_joint_state_waits_for_it():
    """Started paused and resumed before the arm reported: waiting (not a crash), and the babbling loop runs."""
    with babble_node([Parameter("start_paused", value=True)]) as node:
        response = node._on_resume(Trigger.Request(), Trigger.Response())
        assert response.success and node.state == "waiting"
        node._on_timer()
        assert node.state == "waiting"


def test_joint_states_that_go_quiet_stop_the_babbling():
    """The arm reported once and then nothing for joint_state_timeout: the reason names the joint states."""
    clock = [50.0]
    with babble_node([Parameter("joint_state_timeout", value=3.0), Parameter("camera_timeout", value=0.0),
                      NO_INPUTS_BUT_JOINT_STATES]) as node:
        node.monotonic = node.driver.clock = lambda: clock[0]
        node.driver._on_joint_states(JointState(name=list(node.driver.joint_names), position=[0.0] * 6))
        node._on_timer()
        assert node.state == "idle" and node._quiet(clock[0]) == ""
        clock[0] += 2.9
        assert node._quiet(clock[0]) == ""
        clock[0] += 0.2
        assert "joint states are quiet: none usable for 3.1 s" in node._quiet(clock[0])


def test_after_a_pause_of_the_node_itself_the_camera_watchdog_reads_the_queued_frames_first():
    """A tick long after the previous one (the process was paused) neither judges the camera's silence nor sends:
    the frame that waited in the queue meanwhile is read first and babbling goes on; a silence seen by a tick on time
    stops it."""
    # camera_timeout 3 s against pauses of 20 s: a busy machine's stall between two calls (seconds) changes nothing.
    with babble_node([Parameter("camera_timeout", value=3.0), NO_INPUTS_BUT_JOINT_STATES]) as node:
        node.driver._on_joint_states(JointState(name=list(node.driver.joint_names), position=[0.0] * 6))
        node._on_timer()
        assert node.state == "idle"
        node.driver.goal = None  # the first tick's move is over
        node.last_camera = node.last_tick = time.monotonic() - 20.0  # paused for 20 s
        sent = node.counts["actions"], node.driver.goal
        node._on_timer()
        assert node.state == "idle" and (node.counts["actions"], node.driver.goal) == sent  # no verdict, no command
        node._on_camera(MarkerPoses())  # the frame that waited in the queue
        node._on_timer()
        assert node.state == "idle"
        node.driver.goal = None  # at rest again (the camera is judged at rest)
        node.last_camera = time.monotonic() - 20.0  # no pause, a silent camera
        node._on_timer()
        assert node.state == "stopped" and "camera is quiet" in node.stop_reason


def test_a_joint_state_beyond_the_limits_is_refused_and_a_halt_stays_within_them():
    """50 rad, -7 rad and 1e308 are refused (counted, named in the stop), never a crash; the halt after them holds the
    last usable posture clamped within the limits less the margin; before any usable joint state it sends nothing."""
    with babble_node([Parameter("camera_timeout", value=0.0)]) as node:
        driver, names = node.driver, list(node.driver.joint_names)
        assert driver.halt() is None and driver.counts["halted_without_goal"] == 1
        driver._on_joint_states(JointState(name=names, position=[1.48, 0.0, 0.0, 0.0, 0.0, -1.5]))
        for bad in (50.0, -7.0, 1e308, 1e6):
            driver._on_joint_states(JointState(name=names, position=[bad] + [0.0] * 5))
        assert driver.counts["joint_states_out_of_range"] == 4 and "joint1 reported at 1e+06" in \
            driver.joint_state_problem
        node._on_timer()  # the loop's next move starts from the last usable posture
        hold = node.driver.halt()
        assert np.allclose(hold, [1.45, 0.0, 0.0, 0.0, 0.0, -1.45])
        assert np.all(hold >= driver.safety.lower) and np.all(hold <= driver.safety.upper)


def test_a_move_from_an_implausible_start_is_refused_not_enumerated():
    """The path check from a start 1e308 or 1e6 rad away is refused at once (it overflowed, or asked the collision
    screen for 2x10^7 postures)."""
    with babble_node() as node:
        goal = np.zeros(6)
        for start in (1e308, 1e6):
            assert node.driver.refusal(goal, start=np.full(6, start)) == "malformed"


def test_the_watched_status_is_this_robots_scheme_node_by_its_exact_name():
    """watch_diagnostics resolves like a topic in babble_node's namespace; a second robot's OK status (whose name
    contains this one's) does not reset the hold of this robot's ERROR."""
    assert watched_status("scheme_node", "/") == "/scheme_node: body scheme"
    assert watched_status("scheme_node", "/robot1") == "/robot1/scheme_node: body scheme"
    assert watched_status("/robot2/scheme_node", "/robot1") == "/robot2/scheme_node: body scheme"
    assert watched_status("", "/robot1") == ""
    with pytest.raises(InvalidInputError, match="watch_diagnostics"):
        watched_status("scheme_node: body scheme", "/")
    clock = [100.0]
    with babble_node([Parameter("error_hold", value=1.0)]) as node:
        node.monotonic = lambda: clock[0]
        error = DiagnosticStatus(name="/scheme_node: body scheme", level=DiagnosticStatus.ERROR, message="invalid")
        other = DiagnosticStatus(name="/robot2/scheme_node: body scheme", level=DiagnosticStatus.OK)
        for _ in range(3):
            node._on_diagnostics(DiagnosticArray(status=[error, other]))
            clock[0] += 0.6
        assert node.state == "stopped" and "ERROR" in node.stop_reason


@pytest.mark.parametrize("name, value, message", [
    ("workspace", [0.0, 1.0], "workspace"), ("max_velocity", 0.0, "limits"), ("dwell", -1.0, "dwell"),
    ("robot", "no_robot", "unknown robot"), ("settle_tolerance", -0.1, "tolerance"),
    ("joint_state_timeout", -1.0, "joint_state_timeout")])
def test_bad_parameters_stop_the_node_with_a_reason(name, value, message):
    with pytest.raises(InvalidInputError, match=message):
        declared_parameters([Parameter(name, value=value)])


# ---------------------------------------------------------------------- pre-flight
@pytest.mark.parametrize("missing, line", [
    ("joint_states", "joint_states: no fresh joint state naming the configured joints on /joint_states: none yet"),
    ("controller", "controller: nothing subscribes to /joint_trajectory_controller/joint_trajectory"),
    ("camera", "camera: no fresh observations on /observations"),
    ("camera_info", "camera_info: no sensor_msgs/CameraInfo on /camera/camera_info"),
    ("markers", "markers: none of [1, 2] seen at the start posture (seen: [7])"),
])
def test_each_missing_input_is_named_in_one_line_and_nothing_is_commanded(missing, line):
    """With one pre-flight input missing, babble_node names it (the log line and /diagnostics) and sends nothing;
    skipping that check on purpose lets it start. Without joint states or frames no marker can have been seen at the
    start posture either: that is the second line (and skipped with it)."""
    follows = ["markers"] if missing in ("joint_states", "camera") else []
    for skip in ([], [missing, *follows]):
        with babble_node([Parameter("part_ids", value=[1, 2]), Parameter("preflight_skip", value=skip)]) as node:
            sent = []
            node.driver.pub_trajectory.publish = sent.append
            controller = None
            if missing != "controller":
                controller = node.create_subscription(JointTrajectory, node.driver.pub_trajectory.topic_name,
                                                      lambda _: None, 10)
            if missing != "joint_states":
                node.driver._on_joint_states(JointState(name=list(node.driver.joint_names), position=[0.0] * 6))
            if missing != "camera":
                node._on_camera(MarkerPoses(marker_ids=[7] if missing == "markers" else [1]))  # 7: not the robot's
            if missing != "camera_info":
                node._on_camera_info(CameraInfo())
            for _ in range(3):
                node._on_timer()
            if skip:
                # Started; it moves once it knows where the arm is (without a joint state the driver sends nothing).
                assert node.state == "idle" and node.preflight == [], (missing, node.preflight)
                assert bool(sent) == (missing != "joint_states")
            else:
                assert node.state == "waiting" and sent == [] and node.counts["actions"] == 0
                assert len(node.preflight) == 1 + len(follows) and node.preflight[0].startswith(line), node.preflight
            del controller


def test_markers_seen_before_the_arm_reported_do_not_count_and_a_refused_joint_state_is_named():
    with babble_node([Parameter("part_ids", value=[1])]) as node:
        node._on_camera(MarkerPoses(marker_ids=[1]))  # before any joint state: not the start posture
        node.driver._on_joint_states(JointState(name=["elbow"], position=[0.0]))
        node._on_camera_info(CameraInfo())
        node._on_timer()
        assert any(line.startswith("markers: none of [1] seen at the start posture (none seen)")
                   for line in node.preflight)
        assert any("the last was refused: JointState lacks joint(s)" in line for line in node.preflight)


def test_one_of_the_robots_markers_seen_at_the_start_posture_passes_and_the_others_are_named():
    """Planned markers face the camera in some postures only: one seen at the start posture shows the camera sees the
    robot and the tracker its markers; the rest are named, not waited for (the rehearsal of docs/your-robot.md waited
    forever: 4 of 5 planned markers face sideways at the zero posture)."""
    with babble_node([Parameter("part_ids", value=[1, 2, 3]),
                      Parameter("preflight_skip", value=["controller", "camera_info"])]) as node:
        node.driver._on_joint_states(JointState(name=list(node.driver.joint_names), position=[0.0] * 6))
        node._on_camera(MarkerPoses(marker_ids=[2]))
        node._on_timer()
        assert node.preflight == [] and node.state != "waiting"
        assert unseen_markers(node._facts) == [1, 3]


def test_an_unknown_check_to_skip_is_refused():
    with pytest.raises(InvalidInputError, match="preflight_skip names unknown checks"):
        with babble_node([Parameter("preflight_skip", value=["cameras"])]):
            pass


def _settle(node, clock, names):
    """Report the arm at its goal until the move has settled (0.1 s ticks)."""
    goal = list(node.driver.goal)
    while node.driver.goal is not None and node.state == "idle":
        clock[0] += 0.1
        node.driver._on_joint_states(JointState(name=names, position=goal))
        node._on_timer()


@contextlib.contextmanager
def watched_camera(*overrides):
    """babble_node on an injected clock (``clock[0]``, from 50 s) with camera_timeout 3 s, its arm reported at zero
    and one camera message: ``(node, clock, joint names)``."""
    clock = [50.0]
    with babble_node([Parameter("camera_timeout", value=3.0), Parameter("joint_state_timeout", value=0.0),
                      Parameter("settle_window", value=0.1), *overrides, NO_INPUTS_BUT_JOINT_STATES]) as node:
        node.monotonic = node.driver.clock = lambda: clock[0]
        names = list(node.driver.joint_names)
        node.driver._on_joint_states(JointState(name=names, position=[0.0] * 6))
        node._on_camera(MarkerPoses())
        yield node, clock, names


def test_the_camera_is_judged_at_rest_only():
    """A slow move (max_velocity 0.5) outlasts camera_timeout with no picture (sim_node renders none while the arm
    moves): babbling goes on; once the arm has settled, camera_timeout without a message stops it."""
    with watched_camera() as (node, clock, names):
        node._on_timer()
        assert node.state == "idle" and node.driver.goal is not None  # the first move went out
        clock[0] += 10.0  # the arm still on its way, no picture for 10 s
        node._on_timer()
        assert node.state == "idle"
        _settle(node, clock, names)
        assert node.driver.goal is None and node.state == "idle"
        rested = clock[0]
        assert node._quiet(rested + 2.5) == ""
        assert "camera is quiet: nothing on the camera topic for 3." in node._quiet(rested + 3.1)


def test_a_dead_camera_stops_babbling_even_with_rests_shorter_than_the_timeout():
    """Without wait_for_frame the arm rests only ``dwell`` (0.3 s) between moves: the silence at rest is summed over
    the rests, so a camera that died stops babbling after about camera_timeout / dwell moves, not never."""
    with watched_camera(Parameter("wait_for_frame", value=False), Parameter("dwell", value=0.3)) as (
            node, clock, names):  # the camera's last message
        for _ in range(200):
            node._on_timer()
            if node.driver.goal is not None:
                clock[0] += 5.0  # a long move
                _settle(node, clock, names)
            clock[0] += 0.1
            if node.state == "stopped":
                break
        assert node.state == "stopped" and "camera is quiet" in node.stop_reason, node.stop_reason
        assert 4 <= node.counts["actions"] <= 30, node.counts


def test_a_camera_message_during_a_move_starts_the_silence_afresh():
    """The moving time before a message is not credited after it: silence at rest counts from the message, less
    only the moving time since it."""
    with watched_camera() as (node, clock, names):
        node._on_timer()
        assert node.driver.goal is not None
        clock[0] += 5.0
        node._on_camera(MarkerPoses())  # a picture halfway through the move
        clock[0] += 5.0
        _settle(node, clock, names)
        rested = clock[0]
        assert 5.0 <= node.moved_since_camera < 5.5  # since the message (and the settling ticks), not 10 s
        assert node._quiet(rested + 2.5) == ""
        assert "camera is quiet" in node._quiet(rested + 3.5)
