"""Tests of chain-consistent targets: the child's observation relative to the parent's predicted pose."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from body_scheme_core.calibration.noise_model import NoiseModel
from body_scheme_core.learning.chain import ChainTargets
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.quality import prediction_errors
from body_scheme_core.learning.tracked import TrackedModel
from body_scheme_core.models.engineered import engineered_models
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.transforms import invert_transform
from body_scheme_core.world import arm_4dof, make_session

CONFIG = BodySchemeConfig()


def _setup(seed=0):
    robot = arm_4dof()
    session = make_session(robot, 5, seed=seed)
    scheme = BodyScheme(robot.marker_ids, robot.root_marker, engineered_models(robot))
    world2root = session.world2root @ robot.marker(robot.root_marker).link2marker
    std = {p: np.array([0.002, 0.003]) for p in robot.marker_ids}
    return robot, session, scheme, world2root, std


def test_a_tree_edges_target_error_is_its_childs_absolute_error():
    """For an edge of the tree the error against the chain-consistent target equals the child's prediction error; its
    thresholds add the uncertainty of the child's predicted pose to the marker's noise."""
    robot, session, scheme, world2root, std = _setup()
    a, obs = session.actions[2], session.observations[2]
    noise = NoiseModel.from_config(scheme.parts, CONFIG)
    chain = ChainTargets(scheme, world2root, a, obs, noise, std=std)
    edges = [(parent, child) for parent, child, _, _ in scheme.edges]
    index, e_t, e_r, theta_t, theta_r = chain.tree_errors(edges)
    for k, (u, v) in zip(index, np.array(edges)[index], strict=True):
        Z, _, _, _ = chain.pair_target(u, v)
        model = scheme.edge_into(v)[2]
        expected = prediction_errors(model.predict(a[None])[0], Z)
        j = list(index).index(k)
        assert_allclose([e_t[j], e_r[j]], expected, atol=1e-9)
        assert theta_t[j] == pytest.approx(math.sqrt(noise.theta_trans**2 + 27 * 0.002**2))
        assert theta_r[j] == pytest.approx(math.sqrt(noise.theta_rot**2 + 27 * 0.003**2))


def test_targets_need_a_trusted_parent_and_an_observed_child():
    """Parts below an edge in mismatch give no target; a remembered model may be compared the other way round."""
    robot, session, scheme, world2root, std = _setup()
    a, obs = session.actions[0], session.observations[0]
    chain = ChainTargets(scheme, world2root, a, obs, NoiseModel.from_config(scheme.parts, CONFIG), untrusted={4, 5},
                         std=std)
    assert chain.orient(4, 3) == (3, 4)
    assert chain.available(3, 4) and not chain.available(4, 5)
    bridge = TrackedModel(0, 5, 2, (1, 2), "gp", "memory", 0)  # nearer part 2 trusted: 2 -> 5, compared inverted
    index, targets = chain.for_entries([bridge])
    assert index.tolist() == [0] and targets.flip.tolist() == [True]
    assert_allclose(targets.Z[0], invert_transform(chain.world2part[2]) @ obs[5])
    reversed_only = TrackedModel(1, 4, 5, (3,), "gp", "tree", 1)
    assert chain.for_entries([reversed_only], reverse=False)[0].size == 0
    candidate = TrackedModel(2, 5, 3, (2,), "gp", "candidate", 2)  # its own direction: parent 5 is not trusted
    assert chain.for_entries([candidate], own=True)[0].size == 0
