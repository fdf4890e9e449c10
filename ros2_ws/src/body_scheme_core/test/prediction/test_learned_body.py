"""The learned body scheme as a kinematic tree and URDF (body_scheme_core.prediction.learned_body)."""

import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.prediction.learned_body import calibration_report, format_report, learned_tree, learned_urdf
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.world import make_session, planar_2dof, random_tree


def _learn(robot, config=None, n=200, seed=0):
    session = make_session(robot, n, seed=seed, sigma_trans=0.005, sigma_rot=math.radians(2.0), visibility=0.95)
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, config, action_lower=robot.action_lower,
                                action_upper=robot.action_upper)
    for actions, observations in zip(session.actions, session.observations, strict=True):
        learner.update(actions, observations)
    assert learner.body_scheme is not None
    return learner, session


def _fk_error(body, scheme, A):
    fk = body.marker_poses(A)
    predicted = scheme.predict_batch(A)
    return max(float(np.abs(fk[p] - predicted[:, k]).max()) for k, p in enumerate(scheme.parts))


@pytest.mark.parametrize("root", [1, 3])
def test_forward_kinematics_of_the_tree_equal_the_body_schemes_prediction(root):
    """Rooted at the base or at the end effector (every edge inverted), the tree predicts what the scheme does."""
    robot = planar_2dof()
    learner, session = _learn(robot)
    scheme = BodyScheme(learner.body_scheme.parts, root, [model for _, _, model, _ in learner.body_scheme.edges])
    assert all(inverted == (root == 3) for _, _, _, inverted in scheme.edges)
    body = learned_tree(scheme, robot.action_joint_names, robot.action_lower, robot.action_upper)
    assert [j.type for j in body.joints] == ["revolute", "revolute"] and body.notes == []
    assert _fk_error(body, scheme, session.actions[:30]) < 1e-9


def test_prismatic_joints_are_exported_as_prismatic():
    """A robot with sliding joints gets prismatic URDF joints whose FK matches."""
    robot = random_tree(3, seed=4, branching=False, prismatic_fraction=1.0)
    learner, session = _learn(robot, n=150)
    body = learned_tree(learner.body_scheme, robot.action_joint_names, robot.action_lower, robot.action_upper)
    assert {j.type for j in body.joints} == {"prismatic"}
    assert _fk_error(body, learner.body_scheme, session.actions[:30]) < 1e-9
    report = calibration_report(body, robot)
    assert all(r["origin_mm"] is None for r in report["joints"]) and report["max_axis_deg"] < 2.0


def test_gp_edges_are_fixed_at_mid_range_and_flagged():
    """Without rigid-joint candidates the edges are GPs: fixed joints, each named in a note and the URDF comment."""
    robot = planar_2dof()
    learner, _ = _learn(robot, BodySchemeConfig(candidate_kinds=("static", "gp")), n=120)
    urdf = learned_urdf(learned_tree(learner.body_scheme, robot.action_joint_names, robot.action_lower,
                                     robot.action_upper, prefix="robot2/"))
    assert urdf.count("NOTE ") == 2 and "gp model" in urdf and 'type="revolute"' not in urdf
    assert 'name="robot2/part_1"' in urdf and 'name="marker_1_joint"' in urdf and "robot2/marker_1_joint" not in urdf
    body = learned_tree(learner.body_scheme, robot.action_joint_names, robot.action_lower, robot.action_upper)
    report = calibration_report(body, robot)
    assert report["joints"] == [] and len(report["fixed"]) == 2 and "gp" in format_report(report)


def test_bad_limits_and_too_few_joint_names_are_refused():
    robot = planar_2dof()
    learner, _ = _learn(robot, n=100)
    with pytest.raises(InvalidInputError, match="limits"):
        learned_tree(learner.body_scheme, robot.action_joint_names, [1.0, 1.0], [0.0, 0.0])
    with pytest.raises(InvalidInputError, match="joint names"):
        learned_tree(learner.body_scheme, ["only_one"], [0.0], [1.0])


def test_a_prefix_goes_on_links_only_joints_keep_the_robots_names():
    """With a prefix (two robots in one TF tree) the robot's JointState names still drive the learned joints, as
    robot_state_publisher's frame_prefix expects; before issue 20 they became ``robot2/joint1``."""
    robot = planar_2dof()
    learner, _ = _learn(robot)
    body = learned_tree(learner.body_scheme, robot.action_joint_names, robot.action_lower, robot.action_upper,
                        prefix="robot2/")
    joints = body.tree.joints
    assert sorted(j.name for j in joints if j.type == "revolute") == sorted(robot.action_joint_names)
    assert all(link.startswith("robot2/") for j in joints for link in (j.parent, j.child))


def _chain_scheme(seed, couplings=(), root=1):
    """A tool-only random tree (markers 1 on the base, 2 on the tool) and a body scheme of one chain between them:
    the specification's chain about a random reference posture, its parameters moved a little (a calibration), with
    ``couplings`` coefficients of 0.3."""
    from body_scheme_core.models import ChainModel, EngineeredModel, chain_from_engineered
    from body_scheme_core.world import KinematicTree, Marker

    tree = random_tree(4, seed=seed, branching=False, prismatic_fraction=0.3)
    last = [j for j in tree.joints if j.action is not None][-1].child
    robot = KinematicTree(tree.joints, [Marker(1, tree.root_link), Marker(2, last)], root_link=tree.root_link)
    rng = np.random.default_rng(seed)
    reference = rng.uniform(robot.action_lower, robot.action_upper) * 0.5
    spec = chain_from_engineered(EngineeredModel.from_tree(robot, 1, 2), reference=reference[list(range(4))])
    chain = ChainModel(1, 2, spec.actions, spec.types, reference=spec.reference, couplings=couplings)
    params = np.concatenate([spec.params_[:-6], np.full(len(couplings), 0.3), spec.params_[-6:]])
    params = chain.form.retract(params[None], rng.normal(0.0, 0.01, (1, chain.form.N_PARAMS)))[0]
    chain._set_fit(chain.form.canonical(params[None])[0], np.eye(chain.form.N_PARAMS) * 1e-6, 0, 0.0)
    return robot, BodyScheme((1, 2), root, [chain])


@pytest.mark.parametrize("root", [1, 2])
@pytest.mark.parametrize("couplings", [(), ((2, 1),)])
def test_a_chain_is_exported_joint_by_joint_through_links_of_its_own(root, couplings):
    """Each joint of a chain becomes a URDF joint named after its action, a coupling a mimic joint; the URDF's
    forward kinematics equal the body scheme's, rooted at either end, and survive a URDF round trip."""
    from body_scheme_core.world import tree_from_urdf

    robot, scheme = _chain_scheme(3, couplings, root)
    body = learned_tree(scheme, robot.action_joint_names, robot.action_lower, robot.action_upper)
    assert [j.name for j in body.joints] == [robot.action_joint(a).name for a in scheme.models[0].actions[::(
        1 if root == 1 else -1)]]
    assert len(body.notes) == len(couplings)
    A = np.random.default_rng(0).uniform(robot.action_lower, robot.action_upper, (20, robot.n_actions))
    assert _fk_error(body, scheme, A) < 1e-9
    again = tree_from_urdf(learned_urdf(body), markers=body.tree.markers)
    np.testing.assert_allclose(again.marker_poses(A[0][list(body.actions)])[2],
                               body.tree.marker_poses(A[0][list(body.actions)])[2], atol=1e-9)


def test_with_the_specification_a_chain_keeps_its_links_and_the_report_compares_every_joint():
    """Calibrated a little away from the specification, the exported chain's unmarked links carry the
    specification's names and sit near its frames; the report lists every joint of the chain, with the small
    deviation, and zero for the specification itself."""
    robot, scheme = _chain_scheme(5)
    body = learned_tree(scheme, robot.action_joint_names, robot.action_lower, robot.action_upper, nominal=robot)
    links = {j.child for j in body.tree.joints}
    assert {robot.action_joint(a).child for a in scheme.models[0].actions[:-1]} <= links
    report = calibration_report(body, robot)
    assert [r["joint"] for r in report["joints"]] == [robot.action_joint(a).name for a in scheme.models[0].actions]
    assert 0.01 < report["max_axis_deg"] < 5.0 and report["max_marker_mm"] < 100.0
    from body_scheme_core.models import EngineeredModel, chain_from_engineered

    exact = chain_from_engineered(EngineeredModel.from_tree(robot, 1, 2), reference=scheme.models[0].reference)
    body = learned_tree(BodyScheme((1, 2), 1, [exact]), robot.action_joint_names, robot.action_lower,
                        robot.action_upper, nominal=robot)
    report = calibration_report(body, robot)
    assert report["max_axis_deg"] < 1e-6 and (report["max_origin_mm"] or 0.0) < 1e-6
    assert report["max_marker_mm"] < 1e-6
