"""System tests of scheme_node: the installed executable as its own process, our messages over real DDS.

The last test reads the body scheme as the ROS toolbox does: markers, PoseArray, /tf and the learned URDF."""

from __future__ import annotations

import json
import pathlib
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseArray
from rclpy.qos import QoSProfile
from scheme_feed import LATCHED, Babbler, Collector, learned_the_tree, scheme_parameters
from sensor_msgs.msg import CameraInfo, JointState
from std_msgs.msg import String, UInt64
from tf2_msgs.msg import TFMessage
from urdf_parser_py.urdf import URDF
from visualization_msgs.msg import Marker, MarkerArray

from body_scheme_core.world import make_session, planar_2dof
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_msgs.srv import GetRobotDescription
from body_scheme_nodes import conversions
from body_scheme_nodes.view import EDGE_COLOURS

pytestmark = pytest.mark.system

def test_scheme_node_learns_structure_over_dds(start_node, ros_node, spin_until):
    """scheme_node, fed a babbling session over DDS, publishes the true body scheme and an OK diagnostic."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=120, seed=0, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", scheme_parameters(tree))
    collector = Collector(ros_node)

    # The latched structure arrives as soon as discovery completes, before any data: the node is up.
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    assert collector.structure.phase == "bootstrapping" and list(collector.structure.edges) == []

    babbler = Babbler(ros_node, session)
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}

    def learned_true_structure():
        s = collector.structure
        return s is not None and {frozenset((e.parent_id, e.child_id)) for e in s.edges} == true_edges \
            and all(e.valid for e in s.edges)

    assert spin_until(learned_true_structure, timeout=60, during=babbler), (
        f"published {babbler.k} samples; last structure {collector.structure}\n{process.output()}")
    assert sorted(collector.structure.part_ids) == sorted(tree.marker_ids)
    # The snapshot for the control node follows the structure on its own latched topic.
    assert spin_until(lambda: collector.snapshot is not None and collector.snapshot.scheme_json, timeout=60)
    scheme, _, lower, _ = conversions.scheme_from_snapshot(collector.snapshot)
    assert {frozenset((p, c)) for p, c, _, _ in scheme.edges} == true_edges
    np.testing.assert_allclose(lower, tree.action_lower)

    def scheme_ok():
        status = collector.diagnostics.get("/scheme_node: body scheme")
        return status is not None and status.level == DiagnosticStatus.OK
    assert spin_until(scheme_ok, timeout=60, during=babbler), collector.diagnostics
    edge_statuses = [name for name in collector.diagnostics if name.startswith("/scheme_node: local model")]
    assert len(edge_statuses) == len(true_edges)
    # The joint fits go on without changing the structure: control_node gets each refitted body scheme.
    # (With the structure alone, a snapshot's step would always be the structure's.)
    assert spin_until(lambda: collector.snapshot.step > collector.structure.step, timeout=60, during=babbler), (
        collector.snapshot.step, collector.structure.step, babbler.k)
    # Nothing learnt, nothing refitted: no snapshot is republished.
    assert spin_until(lambda: babbler.k == session.n_steps and _values(collector).get("pending_samples") == "0"
                      and _values(collector).get("pairing_waiting") == "0", timeout=60, during=babbler), babbler.k
    # A refit of the last step goes out right after the next /diagnostics array (the same timer): two arrays on, none
    # is left; three more arrays (three periods of the node's timer, however slow the machine) bring no snapshot.
    arrays = collector.n_diagnostics
    assert spin_until(lambda: collector.n_diagnostics >= arrays + 2, timeout=60)
    last, arrays = collector.snapshot, collector.n_diagnostics
    assert spin_until(lambda: collector.n_diagnostics >= arrays + 3, timeout=60)
    assert collector.snapshot is last, (last.step, collector.snapshot.step)


def test_malformed_input_is_counted_and_the_node_keeps_learning(start_node, ros_node, spin_until):
    """NaN poses, zero quaternions, unknown ids, length mismatches and backward stamps are counted, not fatal."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=120, seed=1, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", scheme_parameters(tree))
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    babbler = Babbler(ros_node, session)
    names = list(tree.action_joint_names)
    now = ros_node.get_clock().now().nanoseconds * 1e-9

    # A command, then observations that are broken in every way the tracker or a bag could break them.
    good = JointState(name=names, position=[0.1, 0.2])
    good.header.stamp = conversions.stamp_from_seconds(now)
    babbler.commands.publish(good)
    broken = conversions.marker_poses_msg(now + 0.005, "camera", {k: np.eye(4) for k in (1, 2, 3, 99)})
    broken.poses[1].pose.position.x = float("nan")          # marker 2: NaN position
    broken.poses[2].pose.orientation.w = 0.0                 # marker 3: zero quaternion
    babbler.observations.publish(broken)                     # marker 99: unknown id
    mismatched = conversions.marker_poses_msg(now + 0.006, "camera", {1: np.eye(4)})
    mismatched.marker_ids = [1, 2]
    babbler.observations.publish(mismatched)
    backwards = JointState(name=names, position=[0.0, 0.0])
    backwards.header.stamp = conversions.stamp_from_seconds(now - 10.0)
    babbler.commands.publish(backwards)
    babbler.commands.publish(JointState(name=["nope"], position=[0.0]))
    nan_command = JointState(name=names, position=[float("nan"), 0.0])
    babbler.commands.publish(nan_command)

    expected = {"rejected.invalid_pose": 2, "rejected.unknown_id": 1, "rejected.bad_observations_message": 1,
                "rejected.out_of_order_command": 1, "rejected.bad_command_message": 2}

    def counted():
        status = collector.diagnostics.get("/scheme_node: body scheme")
        values = {} if status is None else {kv.key: kv.value for kv in status.values}
        return all(values.get(key) == str(count) for key, count in expected.items())

    assert spin_until(counted, timeout=60), (collector.diagnostics.get("/scheme_node: body scheme"), process.output())
    # ... and the node still learns from the good data that follows.
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: learned_the_tree(collector, true_edges), timeout=60, during=babbler), process.output()
    assert process.process.poll() is None


def test_kill_and_restart_restores_the_checkpoint(start_node, ros_node, spin_until, tmp_path):
    """After kill -9, a restarted scheme_node restores its checkpoint and publishes the same body scheme."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=150, seed=2, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    checkpoint = tmp_path / "state.json"
    parameters = dict(scheme_parameters(tree), checkpoint_path=str(checkpoint), checkpoint_period=0.5)
    first = start_node("body_scheme_nodes", "scheme_node", parameters)
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=60), first.output()  # discovery done
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    babbler = Babbler(ros_node, session)
    assert spin_until(lambda: learned_the_tree(collector, true_edges), timeout=60, during=babbler), first.output()

    def saved_step():
        try:
            return json.loads(checkpoint.read_text())["state"]["step"]
        except (OSError, ValueError, KeyError):
            return -1

    # Queued samples may still change the tree (bootstrapping goes on): wait until the checkpoint holds every step.
    # Diagnostics and checkpoints run on their own timers, so both may lag the structure: wait for both to reach it.
    assert spin_until(lambda: collector.step is not None and saved_step() == collector.step
                      and collector.step >= collector.structure.step, timeout=60)
    learned = [(e.parent_id, e.child_id, e.description) for e in collector.structure.edges]
    first.kill()  # SIGKILL: no clean shutdown, no final save

    collector.structure = None
    second = start_node("body_scheme_nodes", "scheme_node", parameters)
    assert spin_until(lambda: collector.structure is not None and collector.structure.edges, timeout=60), \
        second.output()
    assert "restored checkpoint" in second.output()
    assert [(e.parent_id, e.child_id, e.description) for e in collector.structure.edges] == learned


def test_kill_9_series_through_replacements_and_reinstatements_restores_every_checkpoint(start_node, ros_node,
                                                                                        spin_until, tmp_path):
    """A session in which a joint blocks, is repaired and blocks again (a replaced model, a reinstated one: models
    with priors), killed with SIGKILL after each change: every restart restores the checkpoint the killed node last
    wrote (it was refused from the first reinstatement on, and learning restarted from step 0), nothing is moved
    aside, and the events of the whole series include the replacement and the reinstatement."""
    from body_scheme_core.world import REPAIR, Fault
    from body_scheme_msgs.msg import SchemeEvent

    tree = planar_2dof()
    block = Fault("block_joint", action_index=1, angle=0.6)
    session = make_session(tree, n_steps=330, seed=4, sigma_trans=0.01, sigma_rot=np.radians(3.0), visibility=0.95,
                           faults=((100, block), (170, REPAIR), (240, block)))
    checkpoint = tmp_path / "state.json"
    # Nothing shed on a busy machine: every sample is learnt, so the events are those of the session.
    parameters = dict(scheme_parameters(tree), checkpoint_path=str(checkpoint), checkpoint_period=0.5,
                      max_sample_age=600.0)
    events = []
    ros_node.create_subscription(SchemeEvent, "body_scheme/events", lambda msg: events.append(msg.kind), 1000)
    collector = Collector(ros_node)
    babbler = Babbler(ros_node, session, period=0.05)

    def saved():
        try:
            return json.loads(checkpoint.read_text())["state"]
        except (OSError, ValueError, KeyError):
            return {"step": -1, "entries": []}

    def saved_step():
        return saved()["step"]

    process, restored, with_priors = start_node("body_scheme_nodes", "scheme_node", parameters), [], 0
    for kill_after in (150, 215, 290, None):  # after the replacement, the reinstatement, the second block
        assert spin_until(lambda: collector.structure is not None and babbler.commands.get_subscription_count() > 0
                          and babbler.observations.get_subscription_count() > 0, timeout=60), process.output()
        if kill_after is None:
            assert spin_until(lambda: babbler.k >= session.n_steps, timeout=120, during=babbler)
            break
        assert spin_until(lambda k=kill_after: babbler.k >= k and saved_step() > 0, timeout=120, during=babbler), \
            process.output()
        process.kill()  # SIGKILL: no clean shutdown, no final save
        state = saved()
        step = state["step"]
        with_priors += any(entry["prior"] is not None for entry in state["entries"])
        collector.structure = None
        process = start_node("body_scheme_nodes", "scheme_node", parameters)
        assert spin_until(lambda p=process: "restored checkpoint" in p.output(), timeout=60), process.output()
        assert f"at step {step}" in process.output(), (step, process.output())
        restored.append(step)
    assert not list(tmp_path.glob("*.corrupt-*")) and restored == sorted(restored) and restored[0] > 100
    assert {"model_replaced", "model_reinstated"} <= set(events), sorted(set(events))
    assert with_priors >= 1  # the states that were refused before: with a prior


# ---------------------------------------------------------------------- hostile input and ROS conventions (issue 12)
SHIPPED_YAML = pathlib.Path(__file__).resolve().parents[1] / "ros2_ws/src/body_scheme_nodes/config/scheme_node.yaml"


def _values(collector, name="/scheme_node: body scheme"):
    status = collector.diagnostics.get(name)
    return {} if status is None else {kv.key: kv.value for kv in status.values}


def test_hostile_values_and_stamps_are_counted_and_learning_goes_on(start_node, ros_node, spin_until):
    """In steady state: a marker at 1e300 m and one at 1e150 m, a command stamped in 2033, a 50 rad command and
    zero-stamped commands. The node stays up, counts each exactly, and keeps learning from the valid traffic."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=500, seed=5, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", scheme_parameters(tree))
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    babbler = Babbler(ros_node, session)
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: learned_the_tree(collector, true_edges), timeout=60, during=babbler), process.output()
    names = list(tree.action_joint_names)

    def publish_pair(position, poses, stamp=None):
        now = ros_node.get_clock().now().nanoseconds * 1e-9 if stamp is None else stamp
        command = JointState(name=names, position=[float(v) for v in position])
        command.header.stamp = conversions.stamp_from_seconds(now)
        babbler.commands.publish(command)
        babbler.observations.publish(conversions.marker_poses_msg(now + 0.005, "camera", poses))

    start = ros_node.get_clock().now().nanoseconds * 1e-9 + 0.1  # after the babbler's last sample, 50 ms apart
    # Markers 1 and 2 where they really are (the camera's origin would be beyond the robot's reach: refused too).
    far = {part: session.observations[0][part] for part in (1, 2) if part in session.observations[0]}
    far[3] = np.eye(4)
    far[3][0, 3] = 1e300
    publish_pair(session.actions[0], far, start)
    far = {part: session.observations[1][part] for part in (1, 2) if part in session.observations[1]}
    far[3] = np.eye(4)
    far[3][0, 3] = 1e150
    publish_pair(session.actions[1], far, start + 0.05)
    publish_pair([50.0, 0.0], session.observations[2], start + 0.10)
    future = JointState(name=names, position=[0.1, 0.1])
    future.header.stamp.sec = 2_000_000_000
    babbler.commands.publish(future)
    spin_until(lambda: False, timeout=0.5)  # the pairs above are learnt (or refused) before zero stamps arrive
    for _ in range(3):
        babbler.commands.publish(JointState(name=names, position=[0.2, 0.1]))  # zero stamp: receipt time
        spin_until(lambda: False, timeout=0.1)
    expected = {"rejected.out_of_workspace": "2", "rejected.future_stamp": "1",
                "rejected.command_out_of_range": "1", "restamped.unstamped": "3"}
    spin_until(lambda: all(_values(collector).get(k) == v for k, v in expected.items()), timeout=15, during=babbler)
    values = _values(collector)
    assert {k: values.get(k) for k in expected} == expected, {k: v for k, v in values.items() if "." in k}
    step = int(_values(collector)["step"])
    assert spin_until(lambda: int(_values(collector)["step"]) >= step + 10, timeout=60, during=babbler), (
        "learning stopped after the hostile messages", _values(collector), process.output())
    assert process.running()
    assert spin_until(lambda: learned_the_tree(collector, true_edges), timeout=60, during=babbler), process.output()


def test_two_namespaced_nodes_run_from_the_shipped_yaml_with_distinct_diagnostics(start_node, ros_node, spin_until):
    """The shipped YAML is keyed /** so it applies under any namespace; diagnostics names carry the node's namespace
    and hardware_id, so two robots in one domain do not collide."""
    collector = Collector(ros_node)
    processes = [start_node("body_scheme_nodes", "scheme_node", {}, ros_args=["--params-file", str(SHIPPED_YAML),
                                                                            "-r", f"__ns:=/{robot}"])
                 for robot in ("robot1", "robot2")]
    names = ["/robot1/scheme_node: body scheme", "/robot2/scheme_node: body scheme"]
    assert spin_until(lambda: all(name in collector.diagnostics for name in names), timeout=60), (
        sorted(collector.diagnostics), [p.output() for p in processes])
    ids = {collector.diagnostics[name].hardware_id for name in names}
    assert ids == {"/robot1/scheme_node", "/robot2/scheme_node"}
    assert all(p.running() for p in processes)


def _bad_checkpoints(valid_text):
    """Name -> content of checkpoints the node must not use: a newer version, truncated, overflowing, another robot."""
    document = json.loads(valid_text)
    newer = dict(document, version=99)
    overflowing = valid_text.replace('"step":', '"step":1e999,"was_step":', 1)
    other = json.loads(valid_text)
    other["state"]["part_ids"] = [4, 5, 6]
    huge = valid_text.replace('"step":', '"step":' + "9" * 5000 + ',"was_step":', 1)  # a crash loop before issue 20
    return {"newer_version": json.dumps(newer), "truncated": valid_text[: len(valid_text) // 2],
            "overflowing_number": overflowing, "another_robot": json.dumps(other), "huge_integer": huge}


@pytest.mark.parametrize("case", ["newer_version", "truncated", "overflowing_number", "another_robot", "huge_integer"])
def test_a_bad_checkpoint_is_moved_aside_never_overwritten(case, start_node, ros_node, spin_until, tmp_path):
    """scheme_node does not use a bad checkpoint: it moves it to <path>.corrupt-<time> unchanged, starts afresh, and
    its own checkpoints then go to the configured path."""
    from body_scheme_core.learning.learner import BodySchemeLearner
    from body_scheme_core.learning.persistence import save_state

    tree = planar_2dof()
    valid = tmp_path / "valid.json"
    save_state(BodySchemeLearner(tree.marker_ids, tree.n_actions), valid)
    content = _bad_checkpoints(valid.read_text())[case]
    checkpoint = tmp_path / "state.json"
    checkpoint.write_text(content)
    parameters = dict(scheme_parameters(tree), checkpoint_path=str(checkpoint), checkpoint_period=0.5)
    process = start_node("body_scheme_nodes", "scheme_node", parameters)
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None and checkpoint.exists()
                      and list(tmp_path.glob("state.json.corrupt-*")), timeout=60), process.output()
    (aside,) = tmp_path.glob("state.json.corrupt-*")
    assert aside.read_text() == content
    assert "not used" in process.output() and process.running()
    assert spin_until(lambda: checkpoint.exists() and json.loads(checkpoint.read_text())["version"] == 1,
                      timeout=60), process.output()


def test_save_and_load_services_touch_only_files_inside_the_state_directory(start_node, ros_node, spin_until,
                                                                              tmp_path):
    """Over DDS: /etc and '..' are refused, a FIFO is refused at once (the node does not freeze), a foreign file is
    not overwritten, another robot's state is not loaded, and a name inside the state directory round-trips."""
    import os

    from body_scheme_core.learning.learner import BodySchemeLearner
    from body_scheme_core.learning.persistence import save_state
    from body_scheme_msgs.srv import StatePath

    tree = planar_2dof()
    state_dir = tmp_path / "states"
    state_dir.mkdir()
    os.mkfifo(state_dir / "fifo.json")
    (state_dir / "notes.json").write_text('{"mine": true}')
    save_state(BodySchemeLearner([4, 5, 6], 1), state_dir / "other_robot.json")
    process = start_node("body_scheme_nodes", "scheme_node", dict(scheme_parameters(tree), state_dir=str(state_dir)))
    save = ros_node.create_client(StatePath, "/scheme_node/save")
    load = ros_node.create_client(StatePath, "/scheme_node/load")
    assert save.wait_for_service(timeout_sec=60) and load.wait_for_service(timeout_sec=60), process.output()

    def call(client, path):
        future = client.call_async(StatePath.Request(path=path))
        assert spin_until(future.done, timeout=60), (path, process.output())
        return future.result()

    for path in ("/etc/x.json", "../x.json", "notes.json"):
        reply = call(save, path)
        assert not reply.success and "refused" in reply.message, (path, reply.message)
    assert (state_dir / "notes.json").read_text() == '{"mine": true}' and not (tmp_path / "x.json").exists()
    for path, reason in (("fifo.json", "not a regular file"), ("/dev/zero", "not a file name inside"),
                         ("other_robot.json", "another robot")):
        reply = call(load, path)
        assert not reply.success and reason in reply.message, (path, reply.message)
    assert call(save, "arm.json").success and call(load, "arm.json").success
    # Another running node's checkpoint (this process holds its lock) and a second name of a state file: refused.
    from body_scheme_nodes.checkpoint import Checkpoint

    held = Checkpoint(state_dir / "held.json")
    try:
        held.write((state_dir / "arm.json").read_text())
        reply = call(save, "held.json")
        assert not reply.success and f"checkpoint of a running node (pid {os.getpid()})" in reply.message, reply
    finally:
        held.close()
    os.link(state_dir / "arm.json", state_dir / "alias.json")
    reply = call(save, "alias.json")
    assert not reply.success and "2 names" in reply.message, reply.message
    assert process.running()


def test_a_request_never_kills_or_starves_the_node(start_node, ros_node, spin_until, tmp_path):
    """~/load of a file with a 5000-digit integer killed the node before issue 20: now a failed reply. 50 concurrent
    ~/get_urdf callers (39 waited forever on a queue of 10): every one gets an answer, the URDF or "busy"."""

    from body_scheme_msgs.srv import GetRobotDescription, StatePath

    tree = planar_2dof()
    state_dir = tmp_path / "states"
    state_dir.mkdir()
    (state_dir / "huge.json").write_text('{"format":"body_scheme_state","version":1,"state":{"step":' + "9" * 5000
                                         + "}}")
    process = start_node("body_scheme_nodes", "scheme_node", dict(scheme_parameters(tree), state_dir=str(state_dir)))
    load = ros_node.create_client(StatePath, "/scheme_node/load")
    assert load.wait_for_service(timeout_sec=60), process.output()
    future = load.call_async(StatePath.Request(path="huge.json"))
    assert spin_until(future.done, timeout=60) and not future.result().success
    assert "load failed" in future.result().message and process.running()

    # Callers that wait together each need a depth of their number (every reply goes to every caller's reader).
    callers = [ros_node.create_client(GetRobotDescription, "/scheme_node/get_urdf", qos_profile=QoSProfile(depth=100))
               for _ in range(50)]
    assert all(c.wait_for_service(timeout_sec=60) for c in callers)
    futures = [c.call_async(GetRobotDescription.Request()) for c in callers]
    assert spin_until(lambda: all(f.done() for f in futures), timeout=60), sum(f.done() for f in futures)
    replies = [f.result().message for f in futures]
    busy = [m for m in replies if m.startswith("busy")]
    assert len(replies) == 50 and all(m.startswith(("busy", "no body scheme yet")) for m in replies), replies
    collector = Collector(ros_node)
    assert spin_until(lambda: _values(collector).get("services.get_urdf.busy") is not None, timeout=60)
    values = _values(collector)
    assert int(values["services.get_urdf.busy"]) == len(busy)
    assert int(values["services.get_urdf.answered"]) == 50 - len(busy) and process.running()


def test_a_checkpoint_path_that_is_a_directory_or_in_use_is_refused_at_start(start_node, tmp_path):
    """A directory was renamed to .corrupt-<time> and replaced by a file before issue 20, and two nodes shared one
    checkpoint without a word: now one FATAL line and exit 1 each, the directory untouched."""
    parameters = {"part_ids": [1, 2], "joint_names": ["a"], "action_lower": [-1.0], "action_upper": [1.0]}
    directory = tmp_path / "state_dir_as_checkpoint"
    directory.mkdir()
    (directory / "keep.txt").write_text("mine")
    refused = start_node("body_scheme_nodes", "scheme_node", dict(parameters, checkpoint_path=str(directory)))
    assert refused.process.wait(timeout=30) == 1
    assert "is a directory" in refused.output() and "FATAL" in refused.output()
    assert (directory / "keep.txt").read_text() == "mine" and not list(tmp_path.glob("*.corrupt-*"))

    checkpoint = str(tmp_path / "shared.json")
    first = start_node("body_scheme_nodes", "scheme_node", dict(parameters, checkpoint_path=checkpoint))
    deadline = time.monotonic() + 30
    while "scheme_node ready" not in first.output() and time.monotonic() < deadline:
        time.sleep(0.1)
    second = start_node("body_scheme_nodes", "scheme_node", dict(parameters, checkpoint_path=checkpoint),
                        ros_args=["-r", "__node:=other_scheme_node"])
    assert second.process.wait(timeout=30) == 1
    assert "in use by another process" in second.output() and "Traceback" not in second.output()
    assert first.running()


@pytest.mark.parametrize("bad, message", [
    ({"part_ids": []}, "part_ids must name at least two distinct parts"),
    ({"checkpoint_period": -5.0}, "checkpoint_period must be"),
    ({"frame_id": 5}, "frame_id"),
])
def test_bad_parameters_are_refused_in_one_line_without_a_traceback(bad, message, start_node):
    """Wrongly typed or out-of-range parameters end the node with exit code 1 and one FATAL line naming them."""
    parameters = dict({"part_ids": [1, 2], "joint_names": ["a"], "action_lower": [-1.0], "action_upper": [1.0]}, **bad)
    process = start_node("body_scheme_nodes", "scheme_node", parameters)
    assert process.process.wait(timeout=30) == 1
    output = process.output()
    assert message in output and "FATAL" in output and "Traceback" not in output, output


def test_fuzz_every_hostile_message_is_counted_exactly_and_learning_is_unharmed(domain_id, ros_env, monkeypatch,
                                                                                tmp_path):
    """About 3,000 messages over DDS (``make fuzz`` runs 11,000): a babbling session with every kind of hostile
    message in between (body_scheme_apps.fuzz.CASES). The node stays up, takes in every message, counts exactly
    what the plan adds up with nothing else refused or shed, and learns the tree it learns without the fuzz."""
    from body_scheme_apps.fuzz import CASES, run_fuzz

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    result = run_fuzz(n_messages=3000, n_steps=300, seed=1, domain=domain_id, env=ros_env, log_dir=tmp_path)
    assert result["ok"], {k: v for k, v in result.items() if k != "cases"}
    assert set(result["cases"]) == set(CASES) and result["published_messages"] >= 2500
    assert result["counted"] == result["expected"] and result["structure"] == result["baseline_structure"]
    # Oversized messages (10^5 joint names, 10^6 markers) froze the node for 77-112 s before issue 20. Not frozen:
    # /diagnostics keeps coming (make fuzz measures the gap against its 2 s target; on a shared machine allow more).
    assert result["counted"]["rejected.oversized_message"] == result["expected"]["rejected.oversized_message"] > 0
    assert result["diagnostics_max_gap_s"] < 10.0


def test_input_without_learning_turns_diagnostics_to_error_until_learning_resumes(start_node, ros_node, spin_until):
    """The stall watchdog: commands keep arriving but none can be learnt (unknown joints); after stall_timeout the
    status is ERROR naming the stall; valid pairs bring it back."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=100, seed=3, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", dict(scheme_parameters(tree), stall_timeout=2.0))
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    publisher = ros_node.create_publisher(JointState, "joint_commands", 10)

    def useless_command():
        command = JointState(name=["elbow_of_another_robot"], position=[0.0])
        command.header.stamp = ros_node.get_clock().now().to_msg()
        publisher.publish(command)

    def status():
        return collector.diagnostics.get("/scheme_node: body scheme")

    assert spin_until(lambda: status() is not None and status().level == DiagnosticStatus.WARN, timeout=60)
    assert spin_until(lambda: status().level == DiagnosticStatus.ERROR, timeout=60, during=useless_command), \
        (status(), process.output())
    assert "nothing learnt" in status().message
    babbler = Babbler(ros_node, session)
    assert spin_until(lambda: status().level != DiagnosticStatus.ERROR and babbler.k > 0, timeout=60, during=babbler), \
        status()
    assert "nothing learnt" not in status().message


def test_under_overload_every_observation_is_accounted_for_and_learning_keeps_to_fresh_samples(start_node, ros_node,
                                                                                                  spin_until):
    """A burst far beyond what the learner takes (5,000 pairs in about a second) with max_sample_age 0.05 s: nothing
    is lost uncounted, the stale samples are shed (counted), learning goes on, and at the end every observation
    message is learnt, refused or shed, which body_scheme/progress reports as all decided."""
    tree = planar_2dof()
    n = 5000
    session = make_session(tree, n_steps=n, seed=4, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=1.0)
    process = start_node("body_scheme_nodes", "scheme_node", dict(scheme_parameters(tree), max_sample_age=0.05))
    collector = Collector(ros_node)
    progress = []
    ros_node.create_subscription(UInt64, "body_scheme/progress", lambda msg: progress.append(msg.data), 10)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    babbler = Babbler(ros_node, session, period=0.0, depth=n)  # as fast as this process publishes
    assert spin_until(lambda: babbler.k == n, timeout=60, during=lambda: [babbler() for _ in range(50)],
                      progress=lambda: babbler.k)

    def count(key):
        return int(_values(collector).get(key, 0))

    def arrived(kind):  # received by scheme_node, or lost inside DDS before it (counted from sequence numbers)
        return count(f"received.{kind}") + count(f"lost.{kind}_messages")

    def settled():  # in one diagnostics message: every message arrived, all taken in, none waiting to be paired or
        # learnt (make test-loaded: the commands' intake can lag the observations', and DDS may overwrite some)
        values = _values(collector)
        return (arrived("observations") == n and arrived("command") == n and values.get("inbox") == "0"
                and count("pending_samples") == 0 and values.get("pairing_waiting") == "0"
                and bool(progress) and progress[-1] == count("received.observations"))

    # 60 s without progress (make test-loaded on a fresh clone gave up at 4937 of 5000 decided after a fixed 60 s)
    assert spin_until(settled, timeout=60, progress=lambda: (progress[-1:], count("received.observations"))), \
        (_values(collector), progress[-1:], process.output())
    assert count("shed.stale_samples") > 0 and 0 < count("step") < n
    # Each observation message became one sample (learnt or shed), was refused by the pairer, or was shed from the
    # inbox before pairing (a loaded machine lets the inbox overflow: CI once had 184 such).
    pairer_refusals = sum(count(f"rejected.{reason}") for reason in
                          ("duplicate", "stale", "settling", "no_command", "out_of_order_observation"))
    learnt_or_shed = (count("step") + count("shed.stale_samples") + count("shed.samples")
                      + count("shed.observations_messages"))
    assert learnt_or_shed + pairer_refusals == count("received.observations"), str(_values(collector))
    # How far learning is behind its input: each learnt sample was at most max_sample_age old when it was taken.
    values = _values(collector)
    assert 0.0 <= float(values["learning_lag_max_ms"]) <= 50.0 + 1e-6
    assert int(values["candidates_raced"]) >= 0 and "candidates" in values
    # Refused unread for its size, an observation message is decided too (rate-0 replays waited forever after one).
    huge = MarkerPoses()
    huge.header.frame_id = "x" * (2 << 20)
    decided = count("received.observations")
    babbler.observations.publish(huge)
    assert spin_until(lambda: progress[-1] == decided + 1, timeout=60), (progress[-1:], _values(collector))
    assert process.process.poll() is None


# ---------------------------------------------------------------------- the ROS toolbox view (issue 13)
class RecordingBabbler(Babbler):
    """A Babbler that remembers which step each observation stamp belongs to."""

    def __init__(self, node, session):
        super().__init__(node, session)
        self.step_of = {}
        publish = self.observations.publish

        def remember(msg):
            self.step_of[round(conversions.seconds_from_stamp(msg.header.stamp), 6)] = self.k
            publish(msg)
        self.observations.publish = remember


def test_markers_poses_tf_and_urdf_show_the_learned_body(start_node, ros_node, spin_until):
    """After learning the 2-DOF arm: the PoseArray and /tf frames are within 3 cm of the true marker poses of the
    step they predict, the markers show axes, green edges, labels with the model kind, uncertainty and observations,
    and the latched robot_description and ~/get_urdf hold a URDF with a revolute joint per action."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=400, seed=4, sigma_trans=0.01, sigma_rot=np.radians(3.0), visibility=0.95)
    parameters = dict(scheme_parameters(tree), tf_prefix="robot1/", view_period=0.05)
    process = start_node("body_scheme_nodes", "scheme_node", parameters)
    collector = Collector(ros_node)
    got = {"markers": None, "poses": [], "tf": [], "description": None}
    ros_node.create_subscription(MarkerArray, "body_scheme/markers", lambda m: got.update(markers=m), 10)
    ros_node.create_subscription(PoseArray, "body_scheme/poses", got["poses"].append, 10)
    ros_node.create_subscription(TFMessage, "/tf", got["tf"].append, 10)
    ros_node.create_subscription(String, "body_scheme/robot_description", lambda m: got.update(description=m),
                                 LATCHED)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    babbler = RecordingBabbler(ros_node, session)
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: learned_the_tree(collector, true_edges) and collector.structure.phase == "steady",
                      timeout=60, during=babbler), process.output()
    got["poses"].clear()
    got["tf"].clear()
    assert spin_until(lambda: len(got["poses"]) >= 5 and len(got["tf"]) >= 5 and got["description"] is not None,
                      timeout=60, during=babbler), process.output()

    ids = sorted(tree.marker_ids)
    for msg in got["poses"][-3:]:
        k = babbler.step_of[round(conversions.seconds_from_stamp(msg.header.stamp), 6)]
        assert msg.header.frame_id == "camera" and len(msg.poses) == len(ids)
        for j, pose in zip(ids, msg.poses, strict=True):
            truth = session.true_poses[k, list(tree.marker_ids).index(j)]
            assert np.linalg.norm([pose.position.x - truth[0, 3], pose.position.y - truth[1, 3],
                                   pose.position.z - truth[2, 3]]) < 0.03, (k, j)
    for msg in got["tf"][-3:]:
        assert [t.child_frame_id for t in msg.transforms] == [f"robot1/marker_{j}" for j in ids]
        assert all(t.header.frame_id == "camera" for t in msg.transforms)
        k = babbler.step_of[round(conversions.seconds_from_stamp(msg.transforms[0].header.stamp), 6)]
        for j, t in zip(ids, msg.transforms, strict=True):
            truth = session.true_poses[k, list(tree.marker_ids).index(j)]
            assert np.linalg.norm([t.transform.translation.x - truth[0, 3], t.transform.translation.y - truth[1, 3],
                                   t.transform.translation.z - truth[2, 3]]) < 0.03

    markers = got["markers"].markers
    assert markers[0].action == Marker.DELETEALL
    by_ns = {}
    for m in markers[1:]:
        by_ns.setdefault(m.ns, []).append(m)
    assert set(by_ns) == {"axes", "edges", "uncertainty", "labels", "observed"}
    assert len(by_ns["axes"][0].points) == 6 * len(ids)
    green = EDGE_COLOURS["valid"]
    assert len(by_ns["edges"]) == 2 and all((e.color.r, e.color.g, e.color.b) == pytest.approx(green)
                                            for e in by_ns["edges"])
    assert sorted(m.text for m in by_ns["labels"]) == ["1", "2: revolute a0", "3: revolute a1"]
    assert all(0 < m.scale.x < 0.2 for m in by_ns["uncertainty"])

    urdf = URDF.from_xml_string(got["description"].data)
    # The robot's joint names (its JointState drives them); the prefix is on the links only.
    assert sorted(j.name for j in urdf.joints if j.type == "revolute") == ["joint1", "joint2"]
    assert all(link.name.startswith("robot1/") for link in urdf.links)
    client = ros_node.create_client(GetRobotDescription, "/scheme_node/get_urdf")
    assert client.wait_for_service(timeout_sec=60)
    future = client.call_async(GetRobotDescription.Request())
    assert spin_until(future.done, timeout=60)
    reply = future.result()
    assert reply.success and URDF.from_xml_string(reply.urdf).name == "learned_body_scheme", reply.message


def test_exploration_suggests_only_postures_the_camera_would_see(start_node, ros_node, spin_until):
    """With ``exploration_camera_info``: suggestions flow while no CameraInfo arrived; a CameraInfo that cannot be a
    camera (uncalibrated, an empty or 1 x 1 image, a focal length of 1e300, a principal point 1e6 px off) is counted
    and ignored, and suggestions go on (such a CameraInfo silently stopped exploration before); a real camera that sees
    too little of the arm (a 1 deg field of view) stops them once a body scheme exists."""
    tree = planar_2dof()
    session = make_session(tree, n_steps=600, seed=2, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    process = start_node("body_scheme_nodes", "scheme_node", {
        **scheme_parameters(tree), "exploration": True, "exploration_candidates": 16,
        "exploration_camera_info": "test_camera_info"})
    collector = Collector(ros_node)
    suggestions = []
    ros_node.create_subscription(JointState, "body_scheme/exploration_command", suggestions.append, 100)
    info = ros_node.create_publisher(CameraInfo, "test_camera_info", 10)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    babbler = Babbler(ros_node, session)
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: learned_the_tree(collector, true_edges), timeout=60, during=babbler), process.output()
    assert suggestions, "no suggestion without a camera constraint"
    uncalibrated = conversions.camera_info_msg(0.0, "camera", 640, 480, np.eye(3))
    uncalibrated.k = [0.0] * 9
    implausible = [
        conversions.camera_info_msg(0.0, "camera", 640, 480, np.array([[500.0, 0, -1e6], [0, 500.0, 240.0],
                                                                       [0, 0, 1.0]])),
        uncalibrated,
        conversions.camera_info_msg(0.0, "camera", 0, 480, np.diag([500.0, 500.0, 1.0])),
        conversions.camera_info_msg(0.0, "camera", 1, 1, np.array([[1e300, 0, 0.5], [0, 1e300, 0.5], [0, 0, 1.0]]))]
    for n, msg in enumerate(implausible, start=1):
        info.publish(msg)
        assert spin_until(lambda n=n: _values(collector).get("rejected.bad_camera_info") == str(n), timeout=60,
                          during=babbler), ({k: v for k, v in _values(collector).items() if "." in k},
                                            process.output())
    step = int(_values(collector)["step"])
    suggestions.clear()
    assert spin_until(lambda: int(_values(collector)["step"]) >= step + 20, timeout=60, during=babbler)
    assert len(suggestions) >= 10, f"{len(suggestions)} suggestions after CameraInfos that are no camera"
    narrow = conversions.camera_info_msg(0.0, "camera", 640, 480, np.array([[38400.0, 0, 320.0],
                                                                            [0, 38400.0, 240.0], [0, 0, 1.0]]))
    for _ in range(5):  # best effort: repeat
        info.publish(narrow)
        spin_until(lambda: False, timeout=0.1, during=babbler)
    step = int(_values(collector)["step"])
    suggestions.clear()
    assert spin_until(lambda: int(_values(collector)["step"]) >= step + 20, timeout=60, during=babbler)
    assert suggestions == [], f"{len(suggestions)} suggestions for a camera that sees nothing"


# ---------------------------------------------------------------------- tool only, the sensor as root (issue 32)
def test_a_tool_seen_past_four_joints_by_a_sensor_at_the_root_is_learnt_as_a_chain(start_node, ros_node,
                                                                                    spin_until):
    """A tracker rigid with the base sees one plate on the tool of a 4-joint arm (a sliding joint among them) and
    nothing else: with ``learner.sensor_root`` the node learns the chain through the unmarked links, and its URDF
    has a joint per action, named after it."""
    from body_scheme_core.control import excursion_plan
    from body_scheme_core.transforms import transform_from_xyz_rpy
    from body_scheme_core.world import KinematicTree, random_tree
    from body_scheme_core.world import Marker as PlateMarker

    arm = random_tree(4, seed=16, branching=False, prismatic_fraction=0.25)
    last = [j for j in arm.joints if j.action is not None][-1].child
    tree = KinematicTree(arm.joints, [PlateMarker(2, last, transform_from_xyz_rpy([0, 0.04, 0.02], [0, 0.4, 0.1]))],
                         root_link=arm.root_link)
    rng = np.random.default_rng(8)
    lo, hi = tree.action_lower, tree.action_upper
    reference = lo + (hi - lo) * rng.uniform(0.35, 0.65, tree.n_actions)
    A = np.vstack([reference[None], excursion_plan(reference, lo, hi, range(4), values=3, span=0.4, rng=rng),
                   rng.uniform(lo, hi, size=(120, 4))])
    session = make_session(tree, len(A), 1, sigma_trans=0.002, sigma_rot=np.radians(0.5), actions=A)
    # Every sample is learnt, however long identifying a chain takes on a busy machine (live, stale ones are shed).
    parameters = dict(scheme_parameters(tree), part_ids=[0, 2], max_sample_age=3600.0, exploration=True,
                      exploration_excursions=True, **{"learner.root": 0, "learner.sensor_root": True})
    process = start_node("body_scheme_nodes", "scheme_node", parameters)
    collector = Collector(ros_node)
    suggested = []
    ros_node.create_subscription(JointState, "body_scheme/exploration_command", suggested.append, 100)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()
    babbler = Babbler(ros_node, session)

    def chain_learnt():
        s = collector.structure
        return s is not None and s.phase == "steady" and [e.kind for e in s.edges] == ["chain"] and s.edges[0].valid

    assert spin_until(chain_learnt, timeout=300, during=babbler), (collector.structure, process.output())
    assert sorted(collector.structure.edges[0].action_indices) == [0, 1, 2, 3]
    # While it bootstrapped, the node suggested the middle of the limits, then each joint moved alone.
    middle = 0.5 * (lo + hi)
    assert len(suggested) >= 5
    np.testing.assert_allclose(suggested[0].position, middle)
    assert all(np.sum(~np.isclose(m.position, middle)) == 1 for m in suggested[1:5])
    client = ros_node.create_client(GetRobotDescription, "/scheme_node/get_urdf")
    assert client.wait_for_service(timeout_sec=60)
    future = client.call_async(GetRobotDescription.Request())
    assert spin_until(future.done, timeout=60)
    urdf = URDF.from_xml_string(future.result().urdf)
    movable = sorted(j.name for j in urdf.joints if j.type in ("revolute", "prismatic"))
    assert movable == sorted(tree.action_joint_names)
