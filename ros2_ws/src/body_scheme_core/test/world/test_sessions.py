"""Tests of world/sessions.py and what a session draws on: robots, observation noise, faults and babbling."""

import math

import numpy as np
import pytest

from body_scheme_core.errors import BodySchemeError, InvalidInputError
from body_scheme_core.models.engineered import EngineeredModel
from body_scheme_core.transforms import (
    invert_transform,
    relative_transform,
    rotational_error,
    transform_from_rotvec,
    transform_from_xyz_rpy,
    translational_error,
)
from body_scheme_core.world import (
    REPAIR,
    Body,
    Fault,
    ObservationModel,
    arm_4dof,
    babble,
    block_joint,
    branching_tree,
    default_world2root,
    deform_limb,
    displace_marker,
    joint_blocked_protocol,
    limb_deformed_protocol,
    make_session,
    planar_2dof,
    powercube_6dof,
    random_tree,
)


def test_robot_builders():
    """Each robot has the documented numbers of actions and markers and a sane size."""
    for tree, m, n in [(planar_2dof(), 2, 3), (arm_4dof(), 4, 5), (powercube_6dof(), 6, 7),
                       (branching_tree(), 5, 6), (random_tree(4, seed=0), 4, 5)]:
        assert tree.n_actions == m
        assert len(tree.marker_ids) == n
    tool = powercube_6dof().marker_poses(np.zeros(6))[7]
    assert 1.1 < tool[2, 3] < 1.3  # the paper's ~1.2 m arm, stretched upright
    assert branching_tree(seed=1).joint("left_elbow").origin[2, 3] != branching_tree(seed=2).joint(
        "left_elbow").origin[2, 3]


def test_random_tree_is_seeded_and_can_be_a_chain():
    """random_tree is reproducible, and branching=False gives a chain."""
    a, b = random_tree(6, seed=3), random_tree(6, seed=3)
    np.testing.assert_array_equal(a.joints[4].origin, b.joints[4].origin)
    chain = random_tree(6, seed=3, branching=False)
    assert chain.marker_tree_edges() == [(k, k + 1) for k in range(1, 7)]


def test_same_seed_gives_identical_session():
    """Two sessions with the same seed are identical; another seed differs."""
    kwargs = dict(faults=[(10, Fault("block_joint", action_index=1, angle=0.3))], sigma_trans=0.05,
                  sigma_rot=0.1, visibility=0.8, above_ground=True)
    s1 = make_session(arm_4dof(), 40, 7, **kwargs)
    s2 = make_session(arm_4dof(), 40, 7, **kwargs)
    s3 = make_session(arm_4dof(), 40, 8, **kwargs)
    np.testing.assert_array_equal(s1.actions, s2.actions)
    np.testing.assert_array_equal(s1.true_poses, s2.true_poses)
    assert [sorted(o) for o in s1.observations] == [sorted(o) for o in s2.observations]
    for o1, o2 in zip(s1.observations, s2.observations, strict=True):
        for marker_id in o1:
            np.testing.assert_array_equal(o1[marker_id], o2[marker_id])
    assert not np.array_equal(s1.actions, s3.actions)


def test_faults_change_only_ground_truth_after_their_step():
    """With the same seed, a fault leaves actions and noise alone and changes truth only from its step on."""
    fault = Fault("block_joint", action_index=5, angle=0.8)
    healthy = make_session(powercube_6dof(), 60, 0, sigma_trans=0.0, sigma_rot=0.0)
    faulty = make_session(powercube_6dof(), 60, 0, faults=[(30, fault)], sigma_trans=0.0, sigma_rot=0.0)
    np.testing.assert_array_equal(healthy.actions, faulty.actions)
    np.testing.assert_array_equal(healthy.true_poses[:30], faulty.true_poses[:30])
    # Blocking the end-effector joint moves only the tool marker (7, last column).
    np.testing.assert_array_equal(healthy.true_poses[30:, :6], faulty.true_poses[30:, :6])
    assert np.all(translational_error(healthy.true_poses[30:, 6], faulty.true_poses[30:, 6]) > 1e-3)
    np.testing.assert_array_equal(faulty.executed[30:, 5], 0.8)
    np.testing.assert_array_equal(faulty.phase, [0] * 30 + [1] * 30)
    assert faulty.faults == [(30, "30:block_joint:5:0.8")]


def test_noise_statistics_match_sigma():
    """Position and rotation errors have RMS sigma_trans and sigma_rot and zero mean over many samples."""
    rng = np.random.default_rng(0)
    sigma_trans, sigma_rot = 0.044, 0.2
    observer = ObservationModel(sigma_trans, sigma_rot, 1.0, rng)
    root2marker = np.tile(transform_from_xyz_rpy([0.3, 0.1, 0.8], [0.2, -0.4, 1.0]), (20000, 1, 1, 1))
    observations = observer.observe_array(root2marker, [5])
    Y = np.stack([o[5] for o in observations])
    X = default_world2root() @ root2marker[:, 0]
    d = Y[:, :3, 3] - X[:, :3, 3]
    np.testing.assert_allclose(np.sqrt(np.mean(np.sum(d ** 2, axis=1))), sigma_trans, rtol=0.02)
    np.testing.assert_allclose(d.std(axis=0), sigma_trans / math.sqrt(3), rtol=0.03)
    np.testing.assert_allclose(d.mean(axis=0), 0.0, atol=1e-3)  # about 5 standard errors
    angles = rotational_error(X, Y)
    np.testing.assert_allclose(np.sqrt(np.mean(angles ** 2)), sigma_rot, rtol=0.02)


def test_noise_free_observation_is_world2root_times_truth():
    """With zero noise and full visibility the observation is world2root @ root2marker."""
    tree = powercube_6dof()
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    world2root = transform_from_xyz_rpy([0.1, 0.2, 3.0], [0.3, 0.2, 0.1])
    observed = ObservationModel(0.0, 0.0, 1.0, 0, world2root=world2root).observe(tree.marker_poses(a))
    assert sorted(observed) == list(tree.marker_ids)
    for marker_id, T in tree.marker_poses(a).items():
        np.testing.assert_allclose(observed[marker_id], world2root @ T, atol=1e-12)
    distance = np.linalg.norm(default_world2root()[:3, 3])
    assert 1.9 < distance < 2.2


def test_visibility_rate_and_always_visible():
    """Markers are seen at the requested rate; always_visible ones every time."""
    session = make_session(powercube_6dof(), 3000, 0, visibility=0.8, always_visible=[1])
    visible = session.visible
    assert visible[:, 0].all()
    np.testing.assert_allclose(visible[:, 1:].mean(), 0.8, atol=0.01)


def test_block_joint_holds_the_angle_and_leaves_original_untouched():
    """A blocked joint ignores its command; the original tree and body are unchanged."""
    tree = arm_4dof()
    body = Body(tree)
    blocked = block_joint(body, 2, 0.5)
    a = np.array([0.1, 0.2, -1.0, 0.3])
    np.testing.assert_array_equal(blocked.execute(a), [0.1, 0.2, 0.5, 0.3])
    expected = tree.marker_poses([0.1, 0.2, 0.5, 0.3])
    for marker_id, T in blocked.true_marker_poses(a).items():
        np.testing.assert_allclose(T, expected[marker_id], atol=1e-12)
    assert body.blocked == {} and Body(tree).execute(a)[2] == -1.0
    with pytest.raises(InvalidInputError, match="outside"):
        block_joint(tree, 2, 10.0)


def test_a_gear_maps_the_command_nonlinearly_and_survives_faults():
    """A nonlinear transmission moves the joint to amplitude sin(frequency a); faults and copies keep it."""
    tree = planar_2dof()
    body = Body(tree, gears={1: (1.2, 1.3)})
    np.testing.assert_allclose(body.execute([0.3, 0.5]), [0.3, 1.2 * math.sin(0.65)])
    np.testing.assert_allclose(body.execute([[0.0, 5.0]])[0, 1], 1.2 * math.sin(1.3 * math.pi / 2))  # clipped first
    assert block_joint(body, 0, 0.2).gears == body.gears and body.copy().gears == body.gears
    assert deform_limb(body, "joint2", 0.1).gears == body.gears
    blocked = block_joint(body, 1, 0.4)
    assert blocked.execute([0.0, 1.0])[1] == 0.4  # a blocked joint ignores the gear too
    with pytest.raises(InvalidInputError, match="gear"):
        Body(tree, gears={1: (2.0, 1.0)})  # would leave the joint's limits


def test_execute_clips_commands_to_limits():
    """Commands beyond the joint limits are clipped, as a real controller would."""
    body = Body(planar_2dof())
    np.testing.assert_allclose(body.execute([[5.0, -5.0]]), [[math.pi / 2, -math.pi / 2]])


def test_deform_limb_bends_and_stretches_downstream_only():
    """Deforming the tool moves only the tool marker, by the requested length and angle."""
    tree = powercube_6dof()
    deformed = deform_limb(tree, "tool_joint", delta_length=0.1, delta_rotvec=[math.pi / 4, 0.0, 0.0])
    origin = deformed.tree.joint("tool_joint").origin
    assert np.linalg.norm(origin[:3, 3]) == pytest.approx(0.25)
    assert rotational_error(origin, tree.joint("tool_joint").origin) == pytest.approx(math.pi / 4)
    np.testing.assert_allclose(tree.joint("tool_joint").origin[:3, 3], [0.0, 0.0, 0.15])  # original untouched
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper, size=(5, 6))
    before, after = tree.marker_poses(a), deformed.true_marker_poses(a)
    for marker_id in range(1, 7):
        np.testing.assert_allclose(after[marker_id], before[marker_id], atol=1e-12)
    assert np.all(translational_error(after[7], before[7]) > 0.1)


def test_deform_limb_by_link_name_bends_its_child_joints():
    """deform_limb(body, 'link2') on the 4-DOF arm bends the middle limb (joint3's origin) by 45 degrees."""
    tree = arm_4dof()
    deformed = deform_limb(tree, "link2", delta_rotvec=[0.0, math.pi / 4, 0.0])
    np.testing.assert_allclose(deformed.tree.joint("joint3").origin[:3, 3],
                               0.4 * np.array([math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4)]), atol=1e-12)
    a = np.zeros(4)
    np.testing.assert_allclose(deformed.true_marker_poses(a)[3], tree.marker_poses(a)[3], atol=1e-12)
    assert translational_error(deformed.true_marker_poses(a)[4], tree.marker_poses(a)[4]) > 0.1
    with pytest.raises(InvalidInputError, match="neither"):
        deform_limb(tree, "nope", delta_length=0.1)


def test_displace_marker_moves_only_that_marker():
    """displace_marker composes delta in the marker frame and leaves other markers and the original alone."""
    tree = branching_tree()
    delta = transform_from_rotvec([0.0, 0.3, 0.0], [0.02, 0.0, 0.05])
    moved = displace_marker(tree, 4, delta)
    a = np.random.default_rng(0).uniform(tree.action_lower, tree.action_upper)
    before, after = tree.marker_poses(a), moved.true_marker_poses(a)
    np.testing.assert_allclose(after[4], before[4] @ delta, atol=1e-12)
    for marker_id in (1, 2, 3, 5, 6):
        np.testing.assert_array_equal(after[marker_id], before[marker_id])
    np.testing.assert_array_equal(tree.marker_poses(a)[4], before[4])


def test_repair_restores_the_original_body():
    """In the joint-blocked protocol, truth equals the nominal FK in blocks 1 and 3 and the blocked FK in 2 and 4."""
    session = joint_blocked_protocol(seed=0, n_per_block=20)
    tree = powercube_6dof()
    nominal = np.stack([tree.marker_poses(session.actions)[i] for i in tree.marker_ids], axis=1)
    blocked_actions = session.actions.copy()
    blocked_actions[:, 5] = 0.8
    blocked = np.stack([tree.marker_poses(blocked_actions)[i] for i in tree.marker_ids], axis=1)
    root2marker = invert_transform(session.world2root) @ session.true_poses
    for block, truth in enumerate([nominal, blocked, nominal, blocked]):
        rows = slice(20 * block, 20 * (block + 1))
        np.testing.assert_allclose(root2marker[rows], truth[rows], atol=1e-12)
    np.testing.assert_array_equal(session.phase, np.repeat([0, 1, 2, 3], 20))
    assert [step for step, _ in session.faults] == [20, 40, 60]
    assert session.faults[1] == (40, "40:repair")


def test_protocols_break_only_the_end_effector_model():
    """Both protocols break the engineered 6->7 model in the fault blocks only; 5->6 stays exact."""
    for session, visibility in [(joint_blocked_protocol(seed=1, n_per_block=30), 0.919),
                                (limb_deformed_protocol(seed=1, n_per_block=30), 0.79)]:
        tree = session.tree
        for parent, child, broken in [(5, 6, False), (6, 7, True)]:
            model = EngineeredModel.from_tree(tree, parent, child)
            error = translational_error(model.predict(session.actions), session.true_relative(parent, child))
            for block in range(4):
                block_error = error[30 * block:30 * (block + 1)]
                if broken and block % 2 == 1:
                    assert block_error.mean() > 0.05
                else:
                    np.testing.assert_allclose(block_error, 0.0, atol=1e-12)
        np.testing.assert_allclose(session.visible.mean(), visibility, atol=0.04)
        assert session.sigma_trans == 0.044


def test_relative_observations_are_inverse_compositions():
    """relative_observations returns Y_i^-1 Y_j at exactly the steps where both markers are visible."""
    session = make_session(planar_2dof(), 50, 0, visibility=0.7)
    steps, Z = session.relative_observations(2, 3)
    both = session.visible[:, 1] & session.visible[:, 2]
    np.testing.assert_array_equal(steps, np.flatnonzero(both))
    for t, z in zip(steps, Z, strict=True):
        np.testing.assert_allclose(z, relative_transform(session.observations[t][2], session.observations[t][3]))
    assert session.true_relative(2, 3).shape == (50, 4, 4)


def test_babbling_within_limits_and_above_ground():
    """Babbled actions stay within the joint limits and keep the chosen markers above the table."""
    tree = powercube_6dof()
    A = babble(tree, 500, np.random.default_rng(0), above_ground=[5, 7], ground_z=0.4)
    assert A.shape == (500, 6)
    assert np.all(A >= tree.action_lower) and np.all(A <= tree.action_upper)
    poses = tree.marker_poses(A)
    assert np.all(poses[5][:, 2, 3] > 0.4) and np.all(poses[7][:, 2, 3] > 0.4)
    unconstrained = tree.marker_poses(babble(tree, 500, np.random.default_rng(0)))
    assert np.any(unconstrained[7][:, 2, 3] < 0.4)
    np.testing.assert_array_equal(babble(tree, 20, 1, above_ground=False), babble(tree, 20, 1))


def test_babbling_gives_up_when_impossible():
    """Rejection sampling raises instead of looping forever when no configuration is acceptable."""
    with pytest.raises(BodySchemeError, match="babbling"):
        babble(planar_2dof(), 10, 0, above_ground=[3], ground_z=5.0, max_draws=1000)


def test_invalid_session_input_rejected():
    """Bad faults, steps and observation settings raise InvalidInputError."""
    with pytest.raises(InvalidInputError, match="kind"):
        Fault("melt")
    with pytest.raises(InvalidInputError, match="outside"):
        make_session(planar_2dof(), 10, 0, faults=[(10, REPAIR)])
    with pytest.raises(InvalidInputError, match="Fault"):
        make_session(planar_2dof(), 10, 0, faults=[(3, "repair")])
    with pytest.raises(InvalidInputError, match="visibility"):
        ObservationModel(visibility=1.5)


def test_protocol_schedule_is_fault_repair_fault_and_has_schedule_entries():
    """The protocols' schedules (defined once, also recorded by the simulator) and their schedule-entry texts."""
    from body_scheme_core.world import PROTOCOL_FAULTS, protocol_schedule

    assert set(PROTOCOL_FAULTS) == {"joint_blocked", "limb_deformed"}
    schedule = protocol_schedule("joint_blocked", 10)
    assert [step for step, _ in schedule] == [10, 20, 30]
    assert [fault.entry for _, fault in schedule] == ["block_joint:5:0.8", "repair", "block_joint:5:0.8"]
    assert protocol_schedule("limb_deformed", 5)[0][1].entry == "deform_limb:tool_joint:0.1:0.7853981633974483:0.0:0.0"
    with pytest.raises(InvalidInputError, match="protocol must be one of"):
        protocol_schedule("nope")
    assert Fault("displace_marker", marker_id=3, delta=np.eye(4)).entry == "displace_marker:3" + ":0.0" * 6
