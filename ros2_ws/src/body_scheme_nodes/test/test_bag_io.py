"""bag_io: sessions written as rosbag2 files and read back as rclpy messages, with clear errors for broken bags."""

import pathlib

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from sensor_msgs.msg import JointState

from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes import conversions
from body_scheme_nodes.bag_io import (
    BagError,
    bag_topics,
    read_messages,
    read_session,
    session_info,
    typestore,
    write_session,
)
from body_scheme_sim.sessions import record_session


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """A 12-step planar session with one fault, as a bag."""
    session = record_session("planar_2dof", 12, seed=0, faults=["6:block_joint:1:0.3"])
    return write_session(session, tmp_path_factory.mktemp("bags") / "planar")


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
    session = read_session(bag)
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
    """A /session/info that is not a JSON object raises BagError."""
    String = typestore().types["std_msgs/msg/String"]
    path = _write(tmp_path / "bad_info", "/session/info", "std_msgs/msg/String", [String(data="{not json")])
    with pytest.raises(BagError, match="not JSON"):
        session_info(path)


def test_missing_bag_raises(tmp_path):
    """A bag that does not exist raises BagError naming it."""
    with pytest.raises(BagError, match="does not exist"):
        read_messages(tmp_path / "nothing")


def test_truncated_bag_raises(bag, tmp_path):
    """A bag whose file was cut in half raises BagError, at open or while reading, never a bare error."""
    cut = tmp_path / "cut"
    cut.mkdir()
    for part in bag.iterdir():
        data = part.read_bytes()
        (cut / part.name).write_bytes(data[: len(data) // 2] if part.suffix == ".mcap" else data)
    with pytest.raises(BagError, match="cut"):
        list(read_messages(cut))


def test_corrupted_bytes_raise(bag, tmp_path):
    """A bag with overwritten bytes inside its compressed message chunk raises BagError."""
    garbled = tmp_path / "garbled"
    garbled.mkdir()
    for part in bag.iterdir():
        data = bytearray(part.read_bytes())
        if part.suffix == ".mcap":
            inside = len(data) // 4  # in the first chunk (the second half holds indexes a reader may skip)
            data[inside:inside + 64] = bytes(range(64))
        (garbled / part.name).write_bytes(bytes(data))
    with pytest.raises(BagError, match="garbled"):
        list(read_messages(garbled))


def test_unexpected_type_on_a_session_topic_raises(tmp_path):
    """/joint_commands recorded as std_msgs/String is refused at once, naming the expected type."""
    String = typestore().types["std_msgs/msg/String"]
    path = _write(tmp_path / "wrong", "/joint_commands", "std_msgs/msg/String", [String(data="a")])
    with pytest.raises(BagError, match="expected sensor_msgs/msg/JointState"):
        read_messages(path)


def test_unknown_type_raises_unless_its_topic_is_left_out(tmp_path):
    """A topic of a type without a known class raises; selecting other topics reads the bag fine."""
    Point = typestore().types["geometry_msgs/msg/Point"]
    path = _write(tmp_path / "point", "/where", "geometry_msgs/msg/Point", [Point(x=1.0, y=2.0, z=3.0)])
    with pytest.raises(BagError, match="does not decode"):
        read_messages(path)
    assert list(read_messages(path, ["/joint_commands"])) == []


def test_message_that_does_not_decode_raises(tmp_path):
    """Raw bytes that are not a CDR JointState raise BagError with the topic named."""
    path = _write(tmp_path / "junk", "/joint_commands", "sensor_msgs/msg/JointState", [b"\x00\x01\x00\x00junk"])
    with pytest.raises(BagError, match="/joint_commands"):
        list(read_messages(path))


# ---------------------------------------------------------------------- sessions written and read back
from rosbags.rosbag2 import Reader  # noqa: E402

from body_scheme_sim.sessions import record_protocol  # noqa: E402


@pytest.fixture(scope="module")
def blocked():
    """A short joint-blocked protocol session (4 blocks of 10 steps), noise mode."""
    return record_protocol("joint_blocked", seed=3, n_per_block=10)


def test_bag_reads_back_with_expected_topics_and_counts(blocked, tmp_path):
    """rosbags reads a written session with every topic, its type and one message per step (images: none)."""
    path = write_session(blocked, tmp_path / "session")
    with Reader(path) as reader:
        counts = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert reader.ros_distro == "jazzy"  # not rosbags' own name
    n = blocked.n_steps
    assert counts == {
        "/session/info": ("std_msgs/msg/String", 1),
        "/joint_commands": ("sensor_msgs/msg/JointState", n),
        "/observations": ("body_scheme_msgs/msg/MarkerPoses", n),
        "/ground_truth/marker_poses": ("body_scheme_msgs/msg/MarkerPoses", n),
        "/ground_truth/joint_states": ("sensor_msgs/msg/JointState", n),
    }


def test_read_bag_gives_back_the_session(blocked, tmp_path):
    """read_session returns the same commands, stamps, observations, ground truth and fault timeline."""
    loaded = read_session(write_session(blocked, tmp_path / "session"))
    np.testing.assert_array_equal(loaded.command_stamps, blocked.command_stamps)
    np.testing.assert_array_equal(loaded.observation_stamps, blocked.observation_stamps)
    np.testing.assert_array_equal(loaded.actions, blocked.actions)
    np.testing.assert_array_equal(loaded.executed, blocked.executed)
    np.testing.assert_allclose(loaded.true_poses, blocked.true_poses, atol=1e-12)
    assert [sorted(o) for o in loaded.observations] == [sorted(o) for o in blocked.observations]
    for read, written in zip(loaded.observations, blocked.observations, strict=True):
        for marker_id in written:
            np.testing.assert_allclose(read[marker_id], written[marker_id], atol=1e-12)
    assert loaded.faults == blocked.faults == [(10, "10:block_joint:5:0.8"), (20, "20:repair"),
                                               (30, "30:block_joint:5:0.8")]
    assert (loaded.joint_names, loaded.marker_ids, loaded.seed, loaded.protocol) == (
        blocked.joint_names, blocked.marker_ids, 3, "joint_blocked")
    np.testing.assert_allclose(loaded.camera.K, blocked.camera.K)
    np.testing.assert_allclose(loaded.camera.world2camera, blocked.camera.world2camera)


def test_images_and_camera_info_are_stored_at_the_requested_steps(tmp_path):
    """With image_every=3 the bag holds rgb8 images and camera infos at steps 0, 3, 6, ... that read back equal."""
    session = record_session("planar_2dof", 8, seed=1, image_every=3)
    assert sorted(session.images) == [0, 3, 6]
    path = write_session(session, tmp_path / "images")
    messages = list(read_messages(path, ["/camera/image_raw", "/camera/camera_info"]))
    assert [m.topic for m in messages].count("/camera/image_raw") == 3
    info = next(m.msg for m in messages if m.topic == "/camera/camera_info")
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), session.camera.K)
    loaded = read_session(path)
    assert sorted(loaded.images) == [0, 3, 6]
    for k, image in session.images.items():
        assert image.shape == (480, 640, 3)
        np.testing.assert_array_equal(loaded.images[k], image)


def test_truncated_bag_raises_bag_error(blocked, tmp_path):
    """A bag whose mcap file was cut short raises BagError naming the bag, not a bare decoding error."""
    path = write_session(blocked, tmp_path / "cut")
    mcap = next(path.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cut"):
        read_session(path)


def test_corrupted_bag_bytes_raise_bag_error(blocked, tmp_path):
    """A bag with overwritten bytes in its middle raises BagError."""
    path = write_session(blocked, tmp_path / "garbled")
    mcap = next(path.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(range(64))
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match="garbled"):
        read_session(path)


def test_missing_bag_raises_bag_error(tmp_path):
    """Reading a bag that does not exist raises BagError."""
    with pytest.raises(BagError, match="does not exist"):
        read_session(tmp_path / "nothing")


def test_bag_without_session_info_is_not_a_session(tmp_path):
    """A valid bag lacking the session topics is rejected with the missing topics named."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    with Writer(tmp_path / "other", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        msg = store.types["std_msgs/msg/String"](data="hello")
        writer.write(connection, 1, store.serialize_cdr(msg, "std_msgs/msg/String"))
    with pytest.raises(BagError, match="not a body scheme session"):
        read_session(tmp_path / "other")


def test_writing_over_an_existing_bag_raises(blocked, tmp_path):
    """write_session never overwrites: an existing directory raises BagError."""
    (tmp_path / "taken").mkdir()
    with pytest.raises(BagError, match="taken"):
        write_session(blocked, tmp_path / "taken")



def _decode_with_other_readers(path):
    """Every message of the bag at ``path`` decoded by rosbags' own deserializer and by the mcap library's ROS 2
    decoder (as Foxglove reads a bag); returns the count per topic."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    store, counts = typestore(), {}
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            store.deserialize_cdr(raw, connection.msgtype)  # strict: raises on bytes past the stream's end
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    decoded = {}
    for mcap_file in sorted(pathlib.Path(path).glob("*.mcap")):
        with open(mcap_file, "rb") as stream:
            for _, channel, _, _ in make_reader(stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
                decoded[channel.topic] = decoded.get(channel.topic, 0) + 1
    assert decoded == counts
    return counts


def test_bags_we_write_decode_with_rosbags_and_the_mcap_ros2_decoder(tmp_path):
    """A JointState of 6 joints came out of rclpy 164 bytes long for a 156-byte CDR stream: rosbags' reader refused
    it ("CDR message size mismatch"). Every message of a session with images now decodes in both readers."""
    session = record_session("powercube_6dof", 6, seed=0, perception="rendered", image_every=3)
    counts = _decode_with_other_readers(write_session(session, tmp_path / "rendered"))
    assert counts["/joint_commands"] == 6 and counts["/camera/image_raw"] == 2


@pytest.mark.parametrize("name", ["joint_blocked_seed0", "limb_deformed_seed0", "rendered_seed0"])
def test_the_shipped_bags_decode_with_rosbags_and_the_mcap_ros2_decoder(name):
    """bags/ (regenerated by make bags) holds no message that another reader refuses."""
    counts = _decode_with_other_readers(pathlib.Path(__file__).resolve().parents[4] / "bags" / name)
    assert counts["/joint_commands"] > 0
