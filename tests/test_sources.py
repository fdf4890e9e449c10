"""Other stacks' recordings (aruco_ros, apriltag_ros, motion capture, reflectors, trajectories, tables) as samples."""

import json

import numpy as np
import pytest
import yaml

from body_scheme_apps.other_stacks import LAYOUTS, write_layout
from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import rotational_error, translational_error
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_nodes import conversions
from body_scheme_nodes.offline_replay import replay_bag
from body_scheme_nodes.settings import SchemeSettings
from body_scheme_nodes.sources import SourceMap, translate


@pytest.fixture(scope="module")
def session():
    return make_session(planar_2dof(), 12, seed=3, sigma_trans=0.01, sigma_rot=np.radians(3.0), visibility=0.8)


@pytest.fixture(scope="module")
def recordings(session, tmp_path_factory):
    root = tmp_path_factory.mktemp("other_stacks")
    return {layout: write_layout(session, root / layout, layout) for layout in LAYOUTS}


@pytest.mark.parametrize("layout", LAYOUTS)
def test_each_layout_gives_the_session_s_own_samples(layout, session, recordings):
    """One command per held pose with its values, and the poses seen while it was held (never the stale ones
    a tracker still shows during the move)."""
    recording, map_path, _ = recordings[layout]
    translation = translate(recording, SourceMap.from_yaml(map_path))
    commands = [item.msg for item in translation.messages if item.topic == "/joint_commands"]
    observations = [item.msg for item in translation.messages if item.topic == "/observations"]
    seen = [k for k in range(session.n_steps) if session.observations[k]]
    assert translation.counts["samples"] == len(commands) == len(observations) == len(seen)
    assert translation.counts["unseen"] == session.n_steps - len(seen)
    for k, command, observation in zip(seen, commands, observations, strict=True):
        _, actions = conversions.actions_from_joint_state(command, session.joint_names)
        np.testing.assert_allclose(actions, session.actions[k], atol=1e-9)
        _, poses, _ = conversions.observations_from_msg(observation)
        assert sorted(poses) == sorted(session.observations[k])
        for marker_id, pose in poses.items():
            assert translational_error(pose, session.observations[k][marker_id]) < 1e-6
            assert rotational_error(pose, session.observations[k][marker_id]) < 1e-6
        # Within scheme_node's default pairing window (settle_time 0 s, max_delay 2 s).
        delay = conversions.seconds_from_stamp(observation.header.stamp) - \
            conversions.seconds_from_stamp(command.header.stamp)
        assert 0 < delay <= 1.0


def test_poses_in_another_frame_are_counted_not_taken(recordings, tmp_path):
    recording, map_path, _ = recordings["apriltag_ros"]
    data = yaml.safe_load(map_path.read_text())
    data["frame"] = "camera_depth_frame"
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(data))
    translation = translate(recording, SourceMap.from_yaml(tmp_path / "map.yaml"))
    assert translation.messages == []
    assert translation.counts["wrong_frame"] > 0 and translation.counts["unseen"] == translation.counts["poses"]


def test_too_few_points_are_counted(recordings, tmp_path):
    recording, map_path, _ = recordings["points"]
    data = yaml.safe_load(map_path.read_text())
    for body in data["bodies"].values():
        body["points"] = {f"/nowhere/{label}" if label.endswith("/c") else label: xyz
                          for label, xyz in body["points"].items()}
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(data))
    translation = translate(recording, SourceMap.from_yaml(tmp_path / "map.yaml"))
    assert translation.messages == [] and translation.counts["too_few_points"] > 0


def test_a_table_s_broken_cells_are_counted(session, tmp_path):
    recording, map_path, _ = write_layout(session, tmp_path / "t", "csv")
    lines = recording.read_text().splitlines()
    lines[1] = lines[1].replace(lines[1].split(",")[1], "oops", 1)          # a joint value: the row
    cells = lines[2].split(",")
    cells[-1] = "nan"                                                         # a quaternion: that pose
    lines[2] = ",".join(cells)
    recording.write_text("\n".join(lines) + "\n")
    translation = translate(recording, SourceMap.from_yaml(map_path))
    assert translation.counts["invalid_row"] == 1 and translation.counts["invalid_pose"] == 1
    assert translation.counts["poses"] == session.n_steps - 1


@pytest.mark.parametrize("text, message", [
    ("bodies: {1: {tf: a}}", "needs 'joints'"),
    ("joints: {names: []}\nbodies: {1: {tf: a}}", "joints.names"),
    ("joints: {names: [j1], still_time: -1}\nbodies: {1: {tf: a}}", "joints.still_time"),
    ("joints: {names: [j1]}\nbodies: {1: {tf: a, topic: /b}}", "exactly one of"),
    ("joints: {names: [j1]}\nbodies: {one: {tf: a}}", "marker ids"),
    ("joints: {names: [j1]}\nbodies: {1: {points: {a: [0, 0, 0], b: [1, 0, 0], c: [2, 0, 0]}}}", "one line"),
    ("joints: {names: [j1]}\nbodies: {1: {points: {a: [0, 0], b: [1, 0, 0], c: [0, 1, 0]}}}", "coordinates"),
    ("joints: {names: [j1]}\nframe: camera\nbodies: {1: {tf: a}}\ntopics: {}", "unknown keys"),
    ("[1, 2]", "expected a mapping"),
])
def test_a_bad_source_map_names_its_mistake(text, message, tmp_path):
    (tmp_path / "map.yaml").write_text(text)
    with pytest.raises(InvalidInputError, match=message):
        SourceMap.from_yaml(tmp_path / "map.yaml")


def test_a_map_that_does_not_fit_the_bag_says_why(recordings, tmp_path):
    recording, map_path, _ = recordings["mocap"]
    data = yaml.safe_load(map_path.read_text())
    data["joints"]["topic"] = "/mocap/body_1/pose"
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InvalidInputError, match="must carry one of"):
        translate(recording, SourceMap.from_yaml(tmp_path / "a.yaml"))
    data["joints"]["topic"] = "/joint_states"
    data["bodies"][1] = {"topic": "/joint_states"}
    (tmp_path / "b.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InvalidInputError, match="body 1's topic /joint_states"):
        translate(recording, SourceMap.from_yaml(tmp_path / "b.yaml"))
    data["joints"]["names"] = ["joint1", "elbow"]
    data["bodies"][1] = {"topic": "/mocap/body_1/pose"}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InvalidInputError, match="names the joints"):
        translate(recording, SourceMap.from_yaml(tmp_path / "c.yaml"))


def test_the_offline_replay_learns_the_true_tree_from_apriltag_ros_tf(tmp_path):
    tree = planar_2dof()
    session = make_session(tree, 60, seed=0, sigma_trans=0.01, sigma_rot=np.radians(3.0))
    recording, map_path, params = write_layout(session, tmp_path / "tags", "apriltag_ros")
    result = replay_bag(recording, SchemeSettings.from_yaml(params), source_map=SourceMap.from_yaml(map_path))
    assert result.imported["samples"] == 60 and not result.rejected
    learned = {frozenset((e["parent"], e["child"])) for e in result.learner.edge_status()}
    assert learned == {frozenset(edge) for edge in tree.marker_tree_edges()}


def test_table_rows_closer_than_the_observation_delay_keep_their_own_poses(tmp_path):
    """Rows 50 ms apart (or without stamps): each observation is the row's own and comes before the next command."""
    rows = [{"stamp": 0.05 * k, "joints": {"j1": 0.1 * k}, "poses": {"1": [0, 0, k + 1.0, 0, 0, 0, 1]}}
            for k in range(4)]
    (tmp_path / "t.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    (tmp_path / "map.yaml").write_text("joints: {names: [j1]}\nframe: table\n")
    translation = translate(tmp_path / "t.jsonl", SourceMap.from_yaml(tmp_path / "map.yaml"))
    stream = [(item.topic, item.msg) for item in translation.messages]
    assert [topic for topic, _ in stream] == ["/joint_commands", "/observations"] * 4
    for k in range(4):
        (_, command), (_, observation) = stream[2 * k], stream[2 * k + 1]
        assert command.position[0] == pytest.approx(0.1 * k) and observation.poses[0].pose.position.z == k + 1.0


def test_malformed_table_rows_are_counted_never_a_crash(tmp_path):
    lines = ['{"stamp": 0, "joints": {"j1": 0}, "poses": [1, 2]}',                 # poses not an object
             '{"stamp": 1, "joints": {"j1": 0}, "poses": null, "points": {"4": [1]}}',   # a point of no body
             '{"stamp": 2, "joints": {"j1": 0}, "poses": {"one": [0, 0, 1, 0, 0, 0, 1]}}',  # not a marker id
             '{"stamp": 3, "joints": {"j1": "x"}}',                                 # a joint value that is no number
             '{"stamp": 2, "joints": {"j1": 0}, "poses": {"1": [0, 0, 1, 0, 0, 0, 1]}}',    # stamp not after row 2's
             '{"stamp": 4, "joints": {"j1": 0}, "poses": {"1": [0, 0, 1, 0, 0, 0]}}',       # six numbers
             '{"stamp": 5, "joints": {"j1": 0}, "poses": {"1": [0, 0, 1, 0, 0, 0, 1]}}']    # fine
    (tmp_path / "t.jsonl").write_text("\n".join(lines) + "\n")
    (tmp_path / "map.yaml").write_text("joints: {names: [j1]}\nframe: table\n")
    translation = translate(tmp_path / "t.jsonl", SourceMap.from_yaml(tmp_path / "map.yaml"))
    assert translation.counts["invalid_row"] == 3 and translation.counts["invalid_pose"] == 3
    assert translation.counts["samples"] == 1 and translation.counts["unseen"] == 3
