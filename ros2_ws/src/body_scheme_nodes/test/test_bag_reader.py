"""bag_reader: recorded sessions decoded into rclpy messages, in log-time order, with clear errors for broken bags."""

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from sensor_msgs.msg import JointState

from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes import conversions
from body_scheme_nodes.bag_reader import BagReadError, bag_topics, read_messages, session_info
from body_scheme_sim.bags import read_bag, typestore, write_bag
from body_scheme_sim.sessions import record_session


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """A 12-step planar session with one fault, as a bag."""
    session = record_session("planar_2dof", 12, seed=0, faults=["6:block_joint:1:0.3"])
    return write_bag(session, tmp_path_factory.mktemp("bags") / "planar")


def _write(path, topic, msgtype, messages):
    """A bag with one topic of ``msgtype`` holding ``messages`` (rosbags messages or raw bytes)."""
    store = typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=store)
        for k, msg in enumerate(messages):
            raw = msg if isinstance(msg, bytes) else store.serialize_cdr(msg, msgtype)
            writer.write(connection, k + 1, raw)
    return path


def test_messages_come_in_log_time_order_as_rclpy_messages(bag):
    """Every message of the bag arrives once, in log-time order, as the generated rclpy class of its type."""
    items = list(read_messages(bag))
    counts = {topic: count for topic, (_, count) in bag_topics(bag).items()}
    assert len(items) == sum(counts.values())
    assert [item.log_time for item in items] == sorted(item.log_time for item in items)
    by_topic = {}
    for item in items:
        by_topic.setdefault(item.topic, []).append(item.msg)
    assert {topic: len(msgs) for topic, msgs in by_topic.items()} == counts
    assert all(isinstance(msg, JointState) for msg in by_topic["/joint_commands"])
    assert all(isinstance(msg, MarkerPoses) for msg in by_topic["/observations"])
    # Each command is followed by its observation.
    topics = [item.topic for item in items if item.topic in ("/joint_commands", "/observations")]
    assert topics == ["/joint_commands", "/observations"] * 12


def test_decoded_messages_equal_the_recorded_session(bag):
    """Through rclpy and conversions, commands and observations equal what the simulator's own reader gives."""
    session = read_bag(bag)
    commands = [item.msg for item in read_messages(bag, ["/joint_commands"])]
    observed = [item.msg for item in read_messages(bag, ["/observations"])]
    names = session.joint_names
    for k, msg in enumerate(commands):
        stamp, actions = conversions.actions_from_joint_state(msg, names)
        np.testing.assert_array_equal(actions, session.actions[k])
        assert round(stamp * 1e9) == pytest.approx(session.command_stamps[k], abs=500)
    for k, msg in enumerate(observed):
        _, poses, rejected = conversions.observations_from_msg(msg)
        assert rejected == [] and sorted(poses) == sorted(session.observations[k])
        for marker_id, pose in poses.items():
            np.testing.assert_allclose(pose, session.observations[k][marker_id], atol=1e-12)


def test_topic_selection_skips_the_others_and_absent_topics(bag):
    """Only the requested topics are read; a requested topic the bag lacks is simply absent."""
    items = list(read_messages(bag, ["/observations", "/camera/image_raw"]))
    assert {item.topic for item in items} == {"/observations"} and len(items) == 12


def test_session_info_gives_the_fault_timeline(bag, tmp_path):
    """session_info parses /session/info; a bag without it gives None."""
    info = session_info(bag)
    assert info["robot"] == "planar_2dof" and info["faults"] == [[6, "6:block_joint:1:0.3"]]
    empty = _write(tmp_path / "no_info", "/joint_commands", "sensor_msgs/msg/JointState", [])
    assert session_info(empty) is None


def test_session_info_that_is_not_json_raises(tmp_path):
    """A /session/info that is not a JSON object raises BagReadError."""
    String = typestore().types["std_msgs/msg/String"]
    path = _write(tmp_path / "bad_info", "/session/info", "std_msgs/msg/String", [String(data="{not json")])
    with pytest.raises(BagReadError, match="not JSON"):
        session_info(path)


def test_missing_bag_raises(tmp_path):
    """A bag that does not exist raises BagReadError naming it."""
    with pytest.raises(BagReadError, match="does not exist"):
        read_messages(tmp_path / "nothing")


def test_truncated_bag_raises(bag, tmp_path):
    """A bag whose file was cut in half raises BagReadError, at open or while reading, never a bare error."""
    cut = tmp_path / "cut"
    cut.mkdir()
    for part in bag.iterdir():
        data = part.read_bytes()
        (cut / part.name).write_bytes(data[: len(data) // 2] if part.suffix == ".mcap" else data)
    with pytest.raises(BagReadError, match="cut"):
        list(read_messages(cut))


def test_corrupted_bytes_raise(bag, tmp_path):
    """A bag with overwritten bytes inside its compressed message chunk raises BagReadError."""
    garbled = tmp_path / "garbled"
    garbled.mkdir()
    for part in bag.iterdir():
        data = bytearray(part.read_bytes())
        if part.suffix == ".mcap":
            inside = len(data) // 4  # in the first chunk (the second half holds indexes a reader may skip)
            data[inside:inside + 64] = bytes(range(64))
        (garbled / part.name).write_bytes(bytes(data))
    with pytest.raises(BagReadError, match="garbled"):
        list(read_messages(garbled))


def test_unexpected_type_on_a_session_topic_raises(tmp_path):
    """/joint_commands recorded as std_msgs/String is refused at once, naming the expected type."""
    String = typestore().types["std_msgs/msg/String"]
    path = _write(tmp_path / "wrong", "/joint_commands", "std_msgs/msg/String", [String(data="a")])
    with pytest.raises(BagReadError, match="expected sensor_msgs/msg/JointState"):
        read_messages(path)


def test_unknown_type_raises_unless_its_topic_is_left_out(tmp_path):
    """A topic of a type without a known class raises; selecting other topics reads the bag fine."""
    Point = typestore().types["geometry_msgs/msg/Point"]
    path = _write(tmp_path / "point", "/where", "geometry_msgs/msg/Point", [Point(x=1.0, y=2.0, z=3.0)])
    with pytest.raises(BagReadError, match="does not decode"):
        read_messages(path)
    assert list(read_messages(path, ["/joint_commands"])) == []


def test_message_that_does_not_decode_raises(tmp_path):
    """Raw bytes that are not a CDR JointState raise BagReadError with the topic named."""
    path = _write(tmp_path / "junk", "/joint_commands", "sensor_msgs/msg/JointState", [b"\x00\x01\x00\x00junk"])
    with pytest.raises(BagReadError, match="/joint_commands"):
        list(read_messages(path))
