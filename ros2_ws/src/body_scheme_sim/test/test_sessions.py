"""Tests of recorded sessions, their rosbag2 files and the shipped sample bags."""

from __future__ import annotations

import json
import pathlib
import re
import shlex

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from body_scheme_core.errors import InvalidInputError
from body_scheme_sim import record
from body_scheme_sim.bags import TOPICS, BagError, read_bag, read_messages, typestore, write_bag
from body_scheme_sim.bench import pose_errors
from body_scheme_sim.sessions import (
    IMAGE_DELAY_NS,
    joint_blocked_protocol,
    limb_deformed_protocol,
    record_session,
)

REPO = pathlib.Path(__file__).resolve().parents[4]
BAGS = REPO / "bags"


@pytest.fixture(scope="module")
def blocked():
    """A short joint-blocked protocol session (4 blocks of 10 steps), noise mode."""
    return joint_blocked_protocol(seed=3, n_per_block=10)


def test_bag_reads_back_with_expected_topics_and_counts(blocked, tmp_path):
    """rosbags reads a written session with every topic, its type and one message per step (images: none)."""
    path = write_bag(blocked, tmp_path / "session")
    with Reader(path) as reader:
        counts = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
    n = blocked.n_steps
    assert counts == {
        "/session/info": ("std_msgs/msg/String", 1),
        "/joint_commands": ("sensor_msgs/msg/JointState", n),
        "/observations": ("body_scheme_msgs/msg/MarkerPoses", n),
        "/ground_truth/marker_poses": ("body_scheme_msgs/msg/MarkerPoses", n),
        "/ground_truth/joint_states": ("sensor_msgs/msg/JointState", n),
    }


def test_read_bag_gives_back_the_session(blocked, tmp_path):
    """read_bag returns the same commands, stamps, observations, ground truth and fault timeline."""
    loaded = read_bag(write_bag(blocked, tmp_path / "session"))
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
    path = write_bag(session, tmp_path / "images")
    messages = read_messages(path)
    assert len(messages["/camera/image_raw"]) == len(messages["/camera/camera_info"]) == 3
    info = messages["/camera/camera_info"][0][1]
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), session.camera.K)
    loaded = read_bag(path)
    assert sorted(loaded.images) == [0, 3, 6]
    for k, image in session.images.items():
        assert image.shape == (480, 640, 3)
        np.testing.assert_array_equal(loaded.images[k], image)


def test_observations_are_stamped_just_after_their_commands(blocked):
    """Each observation is stamped IMAGE_DELAY_NS after its command, before the next command."""
    delays = blocked.observation_stamps - blocked.command_stamps
    assert np.all(delays == IMAGE_DELAY_NS)
    assert np.all(np.diff(blocked.command_stamps) > IMAGE_DELAY_NS)


def test_blocked_joint_ignores_commands_only_in_fault_blocks(blocked):
    """The end-effector joint sits at 0.8 rad in blocks 2 and 4 and follows its commands in blocks 1 and 3."""
    n = 10
    for block, is_blocked in enumerate((False, True, False, True)):
        steps = slice(block * n, (block + 1) * n)
        if is_blocked:
            np.testing.assert_allclose(blocked.executed[steps, 5], 0.8)
        else:
            np.testing.assert_allclose(blocked.executed[steps], blocked.actions[steps])
        np.testing.assert_allclose(blocked.executed[steps, :5], blocked.actions[steps, :5])
    assert blocked.phase.tolist() == [0] * 10 + [1] * 10 + [2] * 10 + [3] * 10


def test_limb_deformation_moves_only_the_tool_marker():
    """Deforming the tool limb moves marker 7 in the fault blocks only, and no other marker ever."""
    session = limb_deformed_protocol(seed=3, n_per_block=5)
    healthy = record_session("powercube_6dof", 20, seed=3, markers_of_interest=(6, 7))  # same commands, no fault
    np.testing.assert_array_equal(session.actions, healthy.actions)
    moved = np.linalg.norm(session.true_poses[:, 6, :3, 3] - healthy.true_poses[:, 6, :3, 3], axis=1)
    normal_steps, deformed_steps = np.r_[0:5, 10:15], np.r_[5:10, 15:20]
    assert np.all(moved[normal_steps] < 1e-9)
    assert np.all(moved[deformed_steps] > 0.05)
    np.testing.assert_allclose(session.true_poses[:, :6], healthy.true_poses[:, :6], atol=1e-9)


def test_same_seed_gives_same_commands_and_noise_gives_different_observations():
    """Equal seeds give equal sessions; another seed gives other commands."""
    a = record_session("planar_2dof", 15, seed=4)
    b = record_session("planar_2dof", 15, seed=4)
    c = record_session("planar_2dof", 15, seed=5)
    np.testing.assert_array_equal(a.actions, b.actions)
    for obs_a, obs_b in zip(a.observations, b.observations, strict=True):
        assert sorted(obs_a) == sorted(obs_b)
        for marker_id in obs_a:
            np.testing.assert_array_equal(obs_a[marker_id], obs_b[marker_id])
    assert not np.allclose(a.actions, c.actions)


def test_rendered_session_observes_through_the_tracker():
    """In rendered mode observations come from the tracker: close to the truth, and only visible-ish markers."""
    session = record_session("powercube_6dof", 12, seed=0, perception="rendered", markers_of_interest=(6, 7))
    errors = pose_errors(session)
    assert errors.shape[0] >= 12 * 3
    assert np.median(errors[:, 0]) < 0.02
    noisy = record_session("powercube_6dof", 12, seed=0, perception="noise", markers_of_interest=(6, 7))
    np.testing.assert_array_equal(session.actions, noisy.actions)
    assert np.median(pose_errors(noisy)[:, 0]) > 0.02  # the paper's 44 mm noise, not the tracker's


@pytest.mark.parametrize("kwargs, message", [
    ({"perception": "telepathy"}, "perception"),
    ({"n_steps": 0}, "n_steps"),
    ({"faults": ["20:repair"]}, "outside"),
    ({"faults": ["3:explode"]}, "unknown kind"),
    ({"image_every": -1}, "image_every"),
])
def test_bad_session_arguments_raise(kwargs, message):
    """Bad perception modes, sizes and fault entries raise InvalidInputError before anything runs."""
    arguments = {"robot": "planar_2dof", "n_steps": 10, "seed": 0, **kwargs}
    with pytest.raises(InvalidInputError, match=message):
        record_session(**arguments)


# ---------------------------------------------------------------------- broken bags
def test_truncated_bag_raises_bag_error(blocked, tmp_path):
    """A bag whose mcap file was cut short raises BagError naming the bag, not a bare decoding error."""
    path = write_bag(blocked, tmp_path / "cut")
    mcap = next(path.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="cut"):
        read_bag(path)


def test_corrupted_bag_bytes_raise_bag_error(blocked, tmp_path):
    """A bag with overwritten bytes in its middle raises BagError."""
    path = write_bag(blocked, tmp_path / "garbled")
    mcap = next(path.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(range(64))
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match="garbled"):
        read_bag(path)


def test_missing_bag_raises_bag_error(tmp_path):
    """Reading a bag that does not exist raises BagError."""
    with pytest.raises(BagError, match="does not exist"):
        read_bag(tmp_path / "nothing")


def test_bag_without_session_info_is_not_a_session(tmp_path):
    """A valid bag lacking the session topics is rejected with the missing topics named."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    with Writer(tmp_path / "other", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        msg = store.types["std_msgs/msg/String"](data="hello")
        writer.write(connection, 1, store.serialize_cdr(msg, "std_msgs/msg/String"))
    with pytest.raises(BagError, match="not a body scheme session"):
        read_bag(tmp_path / "other")


def test_writing_over_an_existing_bag_raises(blocked, tmp_path):
    """write_bag never overwrites: an existing directory raises BagError."""
    (tmp_path / "taken").mkdir()
    with pytest.raises(BagError, match="taken"):
        write_bag(blocked, tmp_path / "taken")


# ---------------------------------------------------------------------- the shipped sample bags
def _readme_commands():
    """``{bag name: argv}`` of the regenerate commands in bags/README.md."""
    commands = {}
    for line in (BAGS / "README.md").read_text().splitlines():
        if line.startswith("python -m body_scheme_sim.record "):
            argv = shlex.split(line)[3:]
            commands[pathlib.Path(argv[argv.index("--out") + 1]).name] = argv
    return commands


def _assert_same(a, b, where):
    """Decoded rosbags messages (dataclasses, arrays, scalars) equal field by field; floats to 1e-9."""
    if hasattr(a, "__dataclass_fields__"):
        assert type(a).__name__ == type(b).__name__, where
        for name in a.__dataclass_fields__:
            if name != "__msgtype__":
                _assert_same(getattr(a, name), getattr(b, name), f"{where}.{name}")
    elif isinstance(a, np.ndarray):
        assert a.shape == b.shape and a.dtype == b.dtype, where
        if a.dtype.kind == "f":
            np.testing.assert_allclose(a, b, atol=1e-9, err_msg=where)
        else:
            np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, float):
        assert a == pytest.approx(b, abs=1e-9), where
    elif isinstance(a, str) and where == "/session/info.data":
        assert _same_json(json.loads(a), json.loads(b)), where
    else:
        assert a == b, where


def _same_json(a, b):
    """JSON values equal; floats to 1e-9."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same_json(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same_json(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float):
        return abs(a - b) <= 1e-9
    return a == b


def test_readme_and_makefile_regenerate_the_shipped_bags():
    """bags/README.md lists one command per shipped bag, and `make bags` runs the same commands."""
    commands = _readme_commands()
    assert sorted(commands) == sorted(p.name for p in BAGS.iterdir() if p.is_dir())
    makefile = re.sub(r"\\\n\s*", "", (REPO / "Makefile").read_text())
    for argv in commands.values():
        assert "python -m body_scheme_sim.record " + " ".join(argv) in makefile


@pytest.mark.parametrize("name", sorted(_readme_commands()))
def test_regenerated_bag_equals_shipped_bag(name, tmp_path):
    """Running a bag's documented command again gives the same decoded messages as the shipped bag."""
    argv = list(_readme_commands()[name])
    argv[argv.index("--out") + 1] = str(tmp_path / name)
    assert record.main(argv) == 0
    shipped, fresh = read_messages(BAGS / name), read_messages(tmp_path / name)
    assert sorted(shipped) == sorted(fresh) and set(shipped) <= set(TOPICS)
    for topic in shipped:
        assert len(shipped[topic]) == len(fresh[topic]), topic
        for k, ((t_a, msg_a), (t_b, msg_b)) in enumerate(zip(shipped[topic], fresh[topic], strict=True)):
            assert t_a == t_b, (topic, k)
            _assert_same(msg_a, msg_b, topic if topic == "/session/info" else f"{topic}[{k}]")
