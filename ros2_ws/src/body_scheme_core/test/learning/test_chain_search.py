"""Finding a chain of joints between two observed parts from scratch: excursions, the dependence test, types, order,
couplings; the specification registered where the markers are; replacements that name a blocked joint; and the
learner that bootstraps, adapts and saves a body scheme of a tool observed past several joints."""

import json
import math

import numpy as np
import pytest

from body_scheme_core.control import excursion_plan
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.learning.chain_refit import chain_replacements, register_chain
from body_scheme_core.learning.chain_search import ChainNotIdentified, find_excursions, identify_chain, same_chain
from body_scheme_core.learning.persistence import encode_state
from body_scheme_core.models import EngineeredModel, chain_from_engineered
from body_scheme_core.transforms import invert_transform, transform_from_rotvec, transform_from_xyz_rpy
from body_scheme_core.world import Fault, KinematicTree, Marker, make_session, random_tree

SIGMA = (0.001, math.radians(0.5))


def _tool_only(n_joints, seed, prismatic_fraction=0.3, dummy=False):
    """A random serial chain of ``n_joints`` marked at its root link (1) and its last link (2); with ``dummy`` one
    more action that moves nothing."""
    tree = random_tree(n_joints, seed=seed, branching=False, prismatic_fraction=prismatic_fraction)
    last = [j for j in tree.joints if j.action is not None][-1].child
    markers = [Marker(1, tree.root_link, transform_from_xyz_rpy([0.05, 0, 0], [0.3, 0, 0])),
               Marker(2, last, transform_from_xyz_rpy([0, 0.04, 0.02], [0, 0.4, 0.1]))]
    marked = KinematicTree(tree.joints, markers, root_link=tree.root_link)
    return marked


def _relative(tree, A, rng, sigma=SIGMA, n_actions=None):
    Z = []
    for a in A:
        poses = tree.marker_poses(a[:tree.n_actions])
        noise = transform_from_rotvec(rng.normal(0, sigma[1], 3), rng.normal(0, sigma[0], 3))
        Z.append(invert_transform(poses[1]) @ poses[2] @ noise)
    return np.array(Z)


def _commands(tree, rng, n_random, extra=0):
    lo, hi = tree.action_lower, tree.action_upper
    m = tree.n_actions + extra
    lo, hi = np.append(lo, [-1.0] * extra), np.append(hi, [1.0] * extra)
    reference = lo + (hi - lo) * rng.uniform(0.35, 0.65, m)
    return np.vstack([reference[None], excursion_plan(reference, lo, hi, range(m), values=3, span=0.4, rng=rng),
                      rng.uniform(lo, hi, size=(n_random, m))])


def test_excursions_are_found_around_the_most_frequent_posture():
    """A reference posture no sample is at, single excursions of three actions and one pair."""
    A = np.array([[1.0, 0, 0], [2.0, 0, 0], [0.5, 1, 0], [0.5, 2, 0], [0.5, 0, 3], [0.5, 1, 3], [0.5, 0, 1]])
    ex = find_excursions(A, range(3))
    assert np.allclose(ex.reference, [0.5, 0, 0]) and ex.at_reference.size == 0
    assert [list(ex.single[j]) for j in range(3)] == [[0, 1], [2, 3], [4, 6]] and list(ex.pairs) == [(1, 2)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_joints_their_types_and_order_are_identified_and_a_dummy_action_is_left_out(seed):
    """Random chains of 5 joints (revolute and prismatic) with an action that moves nothing: the chain's actions in
    the true order, the true types, and predictions within the noise at postures it never saw."""
    rng = np.random.default_rng(seed)
    tree = _tool_only(5, seed + 10)
    A = _commands(tree, rng, 30, extra=1)
    model = identify_chain(A, _relative(tree, A, rng), (SIGMA[0] / math.sqrt(3), SIGMA[1] / math.sqrt(3)), 1, 2,
                           range(tree.n_actions + 1))
    assert same_chain(model, chain_from_engineered(EngineeredModel.from_tree(tree, 1, 2)))
    test = rng.uniform(tree.action_lower, tree.action_upper, size=(50, tree.n_actions))
    true = np.array([invert_transform(tree.marker_poses(a)[1]) @ tree.marker_poses(a)[2] for a in test])
    predicted = model.predict(np.hstack([test, np.zeros((50, 1))]))
    assert np.median(np.linalg.norm(predicted[:, :3, 3] - true[:, :3, 3], axis=1)) < 2e-3


def test_without_excursions_a_chain_is_not_identified_yet():
    """Random babbling alone says nothing about single joints: ChainNotIdentified, not a wrong chain."""
    rng = np.random.default_rng(3)
    tree = _tool_only(4, 5)
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(40, tree.n_actions))
    with pytest.raises(ChainNotIdentified, match="no excursion"):
        identify_chain(A, _relative(tree, A, rng), SIGMA, 1, 2, range(tree.n_actions))


def test_a_coupled_joint_is_found_from_the_samples_that_move_two_commands():
    """Fanuc-like: joint 2's command is never moved alone, only with joint 3's against it so that joint 3 stands
    still (its value is q3 + q2): the coupling is found and the chain explains every sample."""
    rng = np.random.default_rng(4)
    tree = _tool_only(4, 8, prismatic_fraction=0.0)
    reference = np.zeros(4)
    single = [reference + v * np.eye(4)[j] for j in (0, 2, 3) for v in (-0.6, -0.3, 0.3, 0.6)]
    coupled = [reference + v * np.array([0, 1.0, -1.0, 0]) for v in (-0.6, -0.3, 0.3, 0.6)]
    A = np.array([reference] + single + coupled)
    physical = A.copy()
    physical[:, 2] = A[:, 2] + A[:, 1]  # the elbow's value follows the shoulder's command
    model = identify_chain(A, _relative(tree, physical, rng), SIGMA, 1, 2, range(4))
    assert model.couplings and np.allclose(model.params_[model.form.COUPLING_STORED_AT], 1.0, atol=0.05)
    errors = np.linalg.norm(model.predict(A)[:, :3, 3] - _relative(tree, physical, rng, (0, 0))[:, :3, 3], axis=1)
    assert errors.max() < 5e-3


def test_the_specification_is_registered_where_the_markers_are():
    """The URDF's chain with markers placed 10 cm and 30 deg off their assumed places: register_chain finds both
    placements, then predicts every sample within the noise."""
    rng = np.random.default_rng(6)
    tree = _tool_only(5, 12)
    spec = chain_from_engineered(EngineeredModel.from_tree(tree, 1, 2))
    G = transform_from_rotvec([0.3, -0.2, 0.4], [0.1, -0.05, 0.08])
    H = transform_from_rotvec([-0.2, 0.1, 0.3], [0.02, 0.03, -0.1])
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(30, tree.n_actions))
    Z = G @ spec.predict(A) @ H
    registered = register_chain(spec, A, Z, SIGMA)
    assert np.abs(registered.predict(A) - Z).max() < 1e-6


def test_a_blocked_joint_is_named_by_the_replacement_without_it():
    """After joint 2 of a 4-joint chain sticks, the chain without it explains the samples since and the full chain
    does not."""
    rng = np.random.default_rng(7)
    tree = _tool_only(4, 14, prismatic_fraction=0.0)
    A = _commands(tree, rng, 30)
    model = identify_chain(A, _relative(tree, A, rng), SIGMA, 1, 2, range(4))
    after = rng.uniform(tree.action_lower, tree.action_upper, size=(12, 4))
    stuck = after.copy()
    stuck[:, 2] = 0.4
    replacements = chain_replacements(model, after, _relative(tree, stuck, rng), np.tile(SIGMA, (12, 1)))
    best = min(replacements, key=lambda m: m.rms_)
    assert best.actions == tuple(a for a in model.actions if a != 2) and best.rms_ < 2.0


@pytest.mark.slow
def test_the_learner_bootstraps_a_tool_past_four_joints_adapts_to_a_block_and_saves_it(tmp_path):
    """Tool-only (a base plate and a tool plate, nothing between): the learner identifies the chain from its
    excursions, ends bootstrapping with it, detects a blocked middle joint, names it, and its state loads again."""
    rng = np.random.default_rng(8)
    tree = _tool_only(4, 16, prismatic_fraction=0.25)
    A = _commands(tree, rng, 80)
    n = len(A)
    session = make_session(tree, n, 1, faults=((70, Fault("block_joint", action_index=1, angle=0.3)),),
                           sigma_trans=0.005, sigma_rot=math.radians(1.0), actions=A)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, BodySchemeConfig(root=1),
                                action_lower=tree.action_lower, action_upper=tree.action_upper)
    events = []
    for k in range(n):
        events += learner.update(A[k], session.observations[k])
        if k == 60:
            (model,) = learner.body_scheme.models
            assert learner.phase == "steady" and model.kind == "chain"
            assert same_chain(model, chain_from_engineered(EngineeredModel.from_tree(tree, 1, 2)))
    replaced = [e for e in events if e.kind == "model_replaced"]
    assert replaced and "joint a1 of the chain no longer moves it" in replaced[0].reason
    detected = next(e.step for e in events if e.kind == "mismatch_detected")
    assert 70 <= detected <= 80
    path = tmp_path / "state.json"
    path.write_text(encode_state(learner, path))
    loaded = BodySchemeLearner.from_state(json.loads(path.read_text())["state"])
    assert np.allclose(loaded.predict(A[-1])[2], learner.predict(A[-1])[2])


def test_a_tracker_that_sweeps_one_joint_at_a_time_gives_the_chain_without_a_noise_prior():
    """The laser-tracker protocol of kinematic calibration: the tracker is the root (``sensor_root``), it sees one
    body on the tool of a six-joint arm, each joint is swept alone (the wrists over two turns), and the noise prior
    is the default (50 mm, 15 deg, far above the tracker's). Simple models of a few actions pass validity at that
    noise; the chain through all six joints is identified where the tree leaves the tool unexplained and dominates
    them: the body scheme is the chain, and it predicts held-out sweeps to the tracker's noise."""
    rng = np.random.default_rng(4)
    tree = _tool_only(6, 21, prismatic_fraction=0.0)
    lo, hi = tree.action_lower, tree.action_upper
    reference = 0.5 * (lo + hi)
    A = []
    for j in range(6):
        span = math.radians(360.0) if j in (3, 5) else 0.4 * (hi[j] - lo[j])
        for value in np.linspace(-span, span, 6) + rng.normal(0.0, 0.01, 6):
            a = reference.copy()
            a[j] = reference[j] + value
            A.append(a)
    A = np.array(A)
    order = rng.permutation(len(A))
    train, test = order[:30], order[30:]
    learner = BodySchemeLearner([0, 2], 6, BodySchemeConfig(root=0, sensor_root=True))
    for a in A[train]:
        pose = tree.marker_poses(a)[2] @ transform_from_rotvec(rng.normal(0, 3e-4, 3), rng.normal(0, 5e-5, 3))
        learner.update(a, {2: pose})
    (model,) = learner.body_scheme.models
    assert model.kind == "chain" and sorted(model.actions) == list(range(6))
    error = [np.linalg.norm(learner.predict(a)[2][:3, 3] - tree.marker_poses(a)[2][:3, 3]) for a in A[test]]
    assert max(error) < 1e-3
