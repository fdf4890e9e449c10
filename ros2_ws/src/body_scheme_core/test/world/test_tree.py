"""Tests of world/tree.py: forward kinematics and tree validation, and the URDF and marker files of a tree."""

import os

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import invert_transform, transform_from_xyz_rpy, xyz_rpy_from_transform
from body_scheme_core.world import (
    Joint,
    KinematicTree,
    Marker,
    branching_tree,
    load_markers_yaml,
    markers_to_yaml,
    planar_2dof,
    powercube_6dof,
    random_tree,
)


def _planar_end_effector(q1, q2, l1=0.5, l2=0.4):
    T = np.eye(4)
    c, s = np.cos(q1 + q2), np.sin(q1 + q2)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [l1 * np.cos(q1) + l2 * c, l1 * np.sin(q1) + l2 * s, 0.1]
    return T


def test_planar_fk_matches_hand_computed_poses():
    """Marker poses of the 2-DOF planar arm equal the textbook formulas."""
    tree = planar_2dof()
    rng = np.random.default_rng(0)
    for q1, q2 in rng.uniform(-1.5, 1.5, size=(10, 2)):
        poses = tree.marker_poses([q1, q2])
        np.testing.assert_allclose(poses[1], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(poses[2][:3, 3], [0.5 * np.cos(q1), 0.5 * np.sin(q1), 0.1], atol=1e-12)
        np.testing.assert_allclose(poses[3], _planar_end_effector(q1, q2), atol=1e-12)


def test_planar_fk_special_configurations():
    """At (pi/2, 0) the arm points along +y; at (0, pi/2) the forearm points along +y."""
    tree = planar_2dof()
    np.testing.assert_allclose(tree.marker_poses([np.pi / 2, 0.0])[3][:3, 3], [0.0, 0.9, 0.1], atol=1e-12)
    np.testing.assert_allclose(tree.marker_poses([0.0, np.pi / 2])[3][:3, 3], [0.5, 0.4, 0.1], atol=1e-12)


def test_batched_fk_equals_single():
    """link_poses and marker_poses over (n, m) equal n single evaluations."""
    tree = random_tree(6, seed=0, prismatic_fraction=0.3)
    rng = np.random.default_rng(0)
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(5, tree.n_actions))
    batch = tree.marker_poses(A)
    for k, a in enumerate(A):
        single = tree.marker_poses(a)
        for marker_id in tree.marker_ids:
            np.testing.assert_allclose(batch[marker_id][k], single[marker_id], atol=1e-12)


def test_relative_transform_is_inverse_composition():
    """relative_transform(i, j) = root2i^-1 root2j, and (i, j) inverts (j, i)."""
    tree = branching_tree(seed=0)
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    poses = tree.marker_poses(a)
    i2j = tree.relative_transform(4, 6, a)
    np.testing.assert_allclose(i2j, invert_transform(poses[4]) @ poses[6], atol=1e-12)
    np.testing.assert_allclose(i2j @ tree.relative_transform(6, 4, a), np.eye(4), atol=1e-12)


def test_prismatic_joint_translates_along_axis():
    """A prismatic joint moves its child by q along the axis expressed in the joint frame."""
    origin = transform_from_xyz_rpy([0.1, 0.0, 0.0], [0.0, 0.0, np.pi / 2])
    tree = KinematicTree([Joint("slide", "prismatic", "base", "slider", origin=origin, axis=[1.0, 0.0, 0.0],
                                lower=0.0, upper=0.5, action=0)], [Marker(0, "slider")])
    np.testing.assert_allclose(tree.marker_poses([0.3])[0][:3, 3], [0.1, 0.3, 0.0], atol=1e-12)


def test_passive_and_fixed_joints_stay_at_zero():
    """A movable joint without action and a fixed joint contribute only their origin."""
    joints = [Joint("active", "revolute", "base", "l1", action=0),
              Joint("passive", "revolute", "l1", "l2", origin=transform_from_xyz_rpy([1, 0, 0], [0, 0, 0])),
              Joint("weld", "fixed", "l2", "l3", origin=transform_from_xyz_rpy([0, 1, 0], [0, 0, 0]))]
    tree = KinematicTree(joints, [Marker(0, "l3")])
    assert tree.n_actions == 1
    np.testing.assert_allclose(tree.marker_poses([0.0])[0][:3, 3], [1.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(tree.marker_poses([np.pi / 2])[0][:3, 3], [-1.0, 1.0, 0.0], atol=1e-12)


def test_action_limits_and_names():
    """action_lower/upper/joint names follow the action indices, not the joint order."""
    joints = [Joint("b", "revolute", "l1", "l2", lower=-0.5, upper=0.5, action=0),
              Joint("a", "prismatic", "base", "l1", axis=[0, 1, 0], lower=0.0, upper=0.2, action=1)]
    tree = KinematicTree(joints, [])
    np.testing.assert_array_equal(tree.action_lower, [-0.5, 0.0])
    np.testing.assert_array_equal(tree.action_upper, [0.5, 0.2])
    assert tree.action_joint_names == ("b", "a")
    assert tree.root_link == "base"
    assert tree.links[0] == "base"


def test_path_actions():
    """path_actions lists the commanded joints between two markers, across the fork."""
    tree = branching_tree()
    assert tree.path_actions(1, 2) == (0,)
    assert tree.path_actions(4, 6) == (1, 2, 3, 4)
    assert tree.path_actions(3, 5) == (1, 3)
    assert tree.path_actions(3, 3) == ()
    assert powercube_6dof().path_actions(6, 7) == (5,)


def test_marker_tree_edges_contract_the_link_tree():
    """Edges connect each marker to the nearest marker towards the root; same-link markers to the first."""
    joints = [Joint("j0", "revolute", "base", "l1", action=0), Joint("j1", "revolute", "l1", "l2", action=1),
              Joint("j2", "revolute", "l2", "l3", action=2), Joint("j3", "revolute", "l1", "l4", action=3)]
    # l1 and l2 carry no marker; l3 carries two; l4 one; base one.
    markers = [Marker(9, "base"), Marker(4, "l3"), Marker(2, "l3"), Marker(7, "l4")]
    tree = KinematicTree(joints, markers)
    assert tree.root_marker == 9
    assert sorted(tree.marker_tree_edges()) == [(2, 4), (9, 2), (9, 7)]


def test_marker_tree_edges_without_root_marker():
    """Without a marker on the root link the top-most markers hang off the root marker."""
    tree = branching_tree()
    markers = [m for m in tree.markers if m.link != "base" and m.link != "torso"]
    tree = KinematicTree(tree.joints, markers)
    edges = tree.marker_tree_edges()
    assert tree.root_marker == 3
    assert sorted(edges) == [(3, 4), (3, 5), (5, 6)]


def test_marker_tree_edges_span_all_markers():
    """The marker tree of random trees has n - 1 edges reaching every marker."""
    for seed in range(5):
        tree = random_tree(7, seed)
        edges = tree.marker_tree_edges()
        assert len(edges) == len(tree.markers) - 1
        assert {child for _, child in edges} == set(tree.marker_ids) - {tree.root_marker}


def test_random_trees_keep_a_marker_on_every_leaf_and_a_commanded_joint():
    """Unmarked links never end a branch, and a body of fixed joints still has one that moves."""
    for seed in range(30):
        tree = random_tree(3, seed, branching=seed % 2 == 0, unmarked_fraction=0.9, fixed_fraction=1.0)
        parents = {j.parent for j in tree.joints}
        leaves = {j.child for j in tree.joints} - parents
        assert leaves <= {m.link for m in tree.markers}
        assert tree.n_actions == 1


@pytest.mark.parametrize("joints, markers, message", [
    ([Joint("a", "revolute", "base", "l1", action=0), Joint("b", "revolute", "l2", "l1", action=1)], [],
     "two parents"),
    ([Joint("a", "revolute", "l1", "l2", action=0), Joint("b", "revolute", "l2", "l1", action=1)], [],
     "root"),
    ([Joint("a", "revolute", "base", "l1", action=0), Joint("b", "revolute", "l2", "l3", action=1)], [],
     "root"),
    ([Joint("a", "revolute", "base", "l1", action=0), Joint("a", "revolute", "l1", "l2", action=1)], [],
     "unique"),
    ([Joint("a", "revolute", "base", "l1", action=0)], [Marker(1, "l9")], "unknown link"),
    ([Joint("a", "revolute", "base", "l1", action=0)], [Marker(1, "l1"), Marker(1, "base")], "unique"),
    ([Joint("a", "revolute", "base", "l1", action=0), Joint("b", "revolute", "l1", "l2", action=0)], [],
     "0..m-1"),
    ([Joint("a", "revolute", "base", "l1", action=1)], [], "0..m-1"),
])
def test_invalid_trees_rejected(joints, markers, message):
    """Forests, cycles, repeated names or ids, unknown links and gaps in the actions are rejected."""
    with pytest.raises(InvalidInputError, match=message):
        KinematicTree(joints, markers)


def test_invalid_joints_rejected():
    """Bad joint types, axes, limits and commanded fixed joints are rejected."""
    with pytest.raises(InvalidInputError, match="type"):
        Joint("a", "floating", "p", "c")
    with pytest.raises(InvalidInputError, match="unit"):
        Joint("a", "revolute", "p", "c", axis=[0.0, 0.0, 2.0])
    with pytest.raises(InvalidInputError, match="limits"):
        Joint("a", "revolute", "p", "c", lower=1.0, upper=-1.0)
    with pytest.raises(InvalidInputError, match="fixed"):
        Joint("a", "fixed", "p", "c", action=0)
    with pytest.raises(InvalidInputError, match="shape"):
        Joint("a", "revolute", "p", "c", origin=np.eye(3))


def test_fk_rejects_wrong_action_length():
    """Action vectors of the wrong length raise InvalidInputError."""
    with pytest.raises(InvalidInputError, match="2 action columns"):
        planar_2dof().marker_poses([0.0, 0.0, 0.0])


def test_joints_and_markers_are_immutable():
    """Joint origins cannot be modified in place, so copies can share them."""
    joint = planar_2dof().joints[0]
    with pytest.raises(ValueError):
        joint.origin[0, 3] = 1.0


def test_urdf_round_trip_gives_identical_fk():
    """from_urdf(to_urdf()) reproduces links, action order, limits and poses."""
    rng = np.random.default_rng(0)
    for tree in [powercube_6dof(), branching_tree(seed=1), random_tree(8, seed=2, prismatic_fraction=0.3)]:
        again = KinematicTree.from_urdf(tree.to_urdf("test"), tree.markers)
        assert set(again.links) == set(tree.links)
        assert again.action_joint_names == tree.action_joint_names
        np.testing.assert_array_equal(again.action_lower, tree.action_lower)
        np.testing.assert_array_equal(again.action_upper, tree.action_upper)
        assert again.marker_tree_edges() == tree.marker_tree_edges()
        A = rng.uniform(tree.action_lower, tree.action_upper, size=(20, tree.n_actions))
        expected, got = tree.marker_poses(A), again.marker_poses(A)
        for marker_id in tree.marker_ids:
            np.testing.assert_allclose(got[marker_id], expected[marker_id], atol=1e-12)


def _pybullet_link_poses(urdf_path_or_text, q, joint_names):
    """World poses of every link from pybullet for joint positions ``q`` given per joint name."""
    import tempfile

    import pybullet

    client = pybullet.connect(pybullet.DIRECT)
    try:
        if urdf_path_or_text.lstrip().startswith("<"):
            with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as stream:
                stream.write(urdf_path_or_text)
            path = stream.name
        else:
            path = urdf_path_or_text
        body = pybullet.loadURDF(path, useFixedBase=True, physicsClientId=client)
        poses = {}
        for index in range(pybullet.getNumJoints(body, physicsClientId=client)):
            info = pybullet.getJointInfo(body, index, physicsClientId=client)
            name = info[1].decode()
            if name in joint_names:
                pybullet.resetJointState(body, index, q[joint_names.index(name)], physicsClientId=client)
        for index in range(pybullet.getNumJoints(body, physicsClientId=client)):
            info = pybullet.getJointInfo(body, index, physicsClientId=client)
            state = pybullet.getLinkState(body, index, computeForwardKinematics=True, physicsClientId=client)
            T = np.eye(4)
            T[:3, :3] = np.reshape(pybullet.getMatrixFromQuaternion(state[5]), (3, 3))
            T[:3, 3] = state[4]
            poses[info[12].decode()] = T
        return poses
    finally:
        pybullet.disconnect(client)


def test_from_urdf_kuka_iiwa_matches_pybullet():
    """pybullet_data's KUKA iiwa gives 7 actions and the same link poses as pybullet's own FK."""
    import pybullet_data
    path = os.path.join(pybullet_data.getDataPath(), "kuka_iiwa", "model.urdf")
    with open(path, encoding="utf-8") as stream:
        tree = KinematicTree.from_urdf(stream.read(), [Marker(1, "lbr_iiwa_link_7")])
    assert tree.n_actions == 7
    assert tree.root_link == "lbr_iiwa_link_0"
    assert np.all(tree.action_lower < 0) and np.all(tree.action_upper > 0)
    # Stretched upright, the flange is about 1.2 m above the base.
    assert 1.0 < tree.marker_poses(np.zeros(7))[1][2, 3] < 1.4
    q = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    expected = _pybullet_link_poses(path, q, list(tree.action_joint_names))
    got = tree.link_poses(q)
    for link, T in expected.items():
        np.testing.assert_allclose(got[link], T, atol=1e-5)


def test_to_urdf_loads_in_pybullet_with_same_fk():
    """The URDF written by to_urdf loads in pybullet and its link poses equal ours."""
    tree = powercube_6dof()
    q = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    expected = _pybullet_link_poses(tree.to_urdf("powercube"), q, list(tree.action_joint_names))
    got = tree.link_poses(q)
    assert set(expected) == set(tree.links) - {tree.root_link}
    for link, T in expected.items():
        np.testing.assert_allclose(got[link], T, atol=1e-5)


def test_from_urdf_joint_actions_mapping():
    """An explicit joint_actions mapping reorders actions and leaves unmapped joints passive."""
    urdf = planar_2dof().to_urdf("planar")
    tree = KinematicTree.from_urdf(urdf, planar_2dof().markers, joint_actions={"joint2": 0})
    assert tree.n_actions == 1
    np.testing.assert_allclose(tree.marker_poses([np.pi / 2])[3][:3, 3], [0.5, 0.4, 0.1], atol=1e-12)
    with pytest.raises(InvalidInputError, match="not movable"):
        KinematicTree.from_urdf(urdf, joint_actions={"nope": 0})


_REVOLUTE = '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/>'


@pytest.mark.parametrize("joint_xml, message", [
    ('<joint name="j" type="floating"><parent link="a"/><child link="b"/></joint>', "floating"),
    ('<joint name="j" type="planar"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/></joint>', "planar"),
    (f'<joint name="k" type="revolute"><parent link="a"/><child link="c"/>{_REVOLUTE}<mimic joint="j"/></joint>'
     f'<joint name="j" type="revolute"><parent link="a"/><child link="b"/>{_REVOLUTE}<mimic joint="k"/></joint>',
     "itself a mimic"),
    (f'<joint name="j" type="revolute"><parent link="a"/><child link="b"/>{_REVOLUTE}<mimic joint="x"/></joint>',
     "does not have"),
    ('<joint name="j" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 one"/></joint>',
     "xyz='0 0 one'"),
    ('<joint name="j" type="revolute"><parent link="a"/></joint>', "child"),
])
def test_from_urdf_rejects_what_a_tree_cannot_hold_in_one_line(joint_xml, message):
    """Floating and planar joints, a mimic of a mimic or of an unknown joint, numbers that do not parse and a joint
    without a child are one-line InvalidInputErrors naming the joint."""
    urdf = f'<robot name="r"><link name="a"/><link name="b"/><link name="c"/>{joint_xml}</robot>'
    with pytest.raises(InvalidInputError, match=message) as error:
        KinematicTree.from_urdf(urdf)
    assert "\n" not in str(error.value)


def _gripper_urdf():
    """A wrist with two fingers: finger2 mimics finger1 with multiplier -0.5 and offset 0.01 (prismatic), plus a
    revolute mimic with multiplier 2 and a transmission and gazebo tag that the reader ignores."""
    return f"""<robot name="g"><link name="base"/><link name="wrist"/><link name="f1"/><link name="f2"/>
      <link name="twin"/>
      <joint name="wrist" type="revolute"><parent link="base"/><child link="wrist"/><origin xyz="0 0 0.3"/>
        {_REVOLUTE}</joint>
      <joint name="finger1" type="prismatic"><parent link="wrist"/><child link="f1"/><origin xyz="0.1 0.02 0"/>
        <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>
      <joint name="finger2" type="prismatic"><parent link="wrist"/><child link="f2"/><origin xyz="0.1 -0.02 0"/>
        <axis xyz="0 -1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/>
        <mimic joint="finger1" multiplier="-0.5" offset="0.01"/></joint>
      <joint name="twin" type="continuous"><parent link="base"/><child link="twin"/><origin xyz="0.2 0 0"/>
        <axis xyz="1 0 0"/><mimic joint="wrist" multiplier="2"/></joint>
      <transmission name="t"><joint name="wrist"><mechanicalReduction>reduction</mechanicalReduction></joint>
      </transmission><gazebo reference="f1"><mu1>0.2</mu1></gazebo></robot>"""


def test_a_mimic_joint_follows_its_action_with_multiplier_and_offset():
    """Mimic joints share their leader's action (no action of their own), sit at multiplier * a + offset, survive a
    URDF round trip, and pybullet (which reads the same URDF) agrees on every link pose."""
    markers = [Marker(1, "base"), Marker(2, "f1"), Marker(3, "f2"), Marker(4, "twin")]
    tree = KinematicTree.from_urdf(_gripper_urdf(), markers)
    assert tree.action_joint_names == ("wrist", "finger1")
    assert tree.joint("finger2").action == 1 and tree.joint("twin").action == 0
    a = np.array([0.3, 0.02])
    assert tree.joint_positions(a) == pytest.approx({"wrist": 0.3, "finger1": 0.02, "finger2": 0.0, "twin": 0.6})
    np.testing.assert_allclose(tree.link_poses([0.0, 0.02])["f2"][:3, 3], [0.1, -0.02, 0.3], atol=1e-12)
    again = KinematicTree.from_urdf(tree.to_urdf("g"), markers)
    for link, T in tree.link_poses(a).items():
        np.testing.assert_allclose(again.link_poses(a)[link], T, atol=1e-12)
    assert tree.path_actions(2, 3) == (1,) and tree.path_actions(1, 4) == (0,)
    positions = tree.joint_positions(a)
    expected = _pybullet_link_poses(tree.to_urdf("g"), list(positions.values()), list(positions))
    for link, T in expected.items():
        np.testing.assert_allclose(tree.link_poses(a)[link], T, atol=1e-5)


def test_a_mimic_of_a_passive_joint_sits_at_its_offset():
    """finger1 has no action (passive, held at 0): finger2, which mimics it, sits at its offset, not at 0."""
    tree = KinematicTree.from_urdf(_gripper_urdf(), [Marker(1, "base")], joint_actions={"wrist": 0})
    assert tree.joint_positions([0.3]) == pytest.approx({"wrist": 0.3, "finger1": 0.0, "finger2": 0.01, "twin": 0.6})


def test_an_engineered_model_through_a_mimic_joint_is_exact():
    """The engineered model between the two fingers predicts the tree's relative pose and its Jacobian matches
    finite differences (the mimic's multiplier enters the chain rule)."""
    from body_scheme_core.models.engineered import EngineeredModel

    tree = KinematicTree.from_urdf(_gripper_urdf(), [Marker(1, "base"), Marker(2, "f1"), Marker(3, "f2")])
    model = EngineeredModel.from_tree(tree, 2, 3)
    rng = np.random.default_rng(0)
    for a in rng.uniform(tree.action_lower, tree.action_upper, size=(5, 2)):
        np.testing.assert_allclose(model.predict(a)[0], tree.relative_transform(2, 3, a), atol=1e-12)
        eps = 1e-6
        numeric = (model.predict(a + [0, eps])[0] - model.predict(a - [0, eps])[0]) / (2 * eps)
        np.testing.assert_allclose(model.jacobian(a)[1], numeric, atol=1e-6)


def test_from_urdf_rejects_malformed_xml():
    """Text that is not URDF raises InvalidInputError."""
    with pytest.raises(InvalidInputError, match="URDF"):
        KinematicTree.from_urdf("<robot name='r'><link name='a'>")


def test_xyz_rpy_round_trip():
    """xyz_rpy_from_transform inverts transform_from_xyz_rpy, including at gimbal lock."""
    rng = np.random.default_rng(0)
    for rpy in list(rng.uniform(-3, 3, size=(10, 3))) + [np.array([0.3, np.pi / 2, -0.2])]:
        T = transform_from_xyz_rpy(rng.normal(size=3), rpy)
        np.testing.assert_allclose(transform_from_xyz_rpy(*xyz_rpy_from_transform(T)), T, atol=1e-12)


def test_marker_yaml_round_trip(tmp_path):
    """markers_to_yaml then load_markers_yaml gives the same markers, from text and from a file."""
    markers = powercube_6dof().markers
    text = markers_to_yaml(markers)
    path = tmp_path / "markers.yaml"
    path.write_text(text)
    for loaded in (load_markers_yaml(text), load_markers_yaml(str(path)), load_markers_yaml(path)):
        assert [m.id for m in loaded] == [m.id for m in markers]
        for a, b in zip(loaded, markers, strict=True):
            assert (a.link, a.size) == (b.link, b.size)
            np.testing.assert_allclose(a.link2marker, b.link2marker, atol=1e-12)


def test_marker_yaml_format():
    """A hand-written placement file with optional fields parses as documented."""
    text = """
markers:
  - {id: 3, link: link2, xyz: [0.1, 0.0, 0.2], rpy: [0.0, 0.0, 1.5707963267948966], size: 0.08}
  - id: 4
    link: base
"""
    a, b = load_markers_yaml(text)
    assert (a.id, a.link, a.size, b.size) == (3, "link2", 0.08, 0.05)
    np.testing.assert_allclose(a.link2marker[:3, 3], [0.1, 0.0, 0.2])
    np.testing.assert_allclose(a.link2marker[:3, 0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(b.link2marker, np.eye(4))


@pytest.mark.parametrize("text, message", [
    ("markers: [{id: 1}]", "needs keys"),
    ("markers: [{id: 1, link: a, colour: red}]", "needs keys"),
    ("markers: [{id: 1, link: a}, {id: 1, link: b}]", "unique"),
    ("markers: [{id: 1, link: a, xyz: [0, 0]}]", "shape"),
    ("foo: []", "single key"),
    ("markers: 3", "list"),
    ("markers: [\n", "YAML"),
])
def test_marker_yaml_rejects_bad_files(text, message):
    """Malformed placement files raise InvalidInputError naming the problem."""
    with pytest.raises(InvalidInputError, match=message):
        load_markers_yaml(text)


def test_copy_and_replace_leave_original_untouched():
    """replace_joint and replace_marker return new trees; the original FK is unchanged."""
    tree = planar_2dof()
    before = tree.marker_poses([0.3, -0.2])
    other = tree.replace_joint("joint2", origin=transform_from_xyz_rpy([0.7, 0, 0], [0, 0, 0]))
    other = other.replace_marker(3, size=0.1)
    copy = tree.copy()
    np.testing.assert_allclose(other.marker_poses([0.0, 0.0])[3][0, 3], 1.1)
    assert other.marker(3).size == 0.1 and tree.marker(3).size == 0.05
    for marker_id, T in before.items():
        np.testing.assert_array_equal(tree.marker_poses([0.3, -0.2])[marker_id], T)
        np.testing.assert_array_equal(copy.marker_poses([0.3, -0.2])[marker_id], T)
