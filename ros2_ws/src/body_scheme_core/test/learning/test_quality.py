"""Tests of prediction errors, the nesting of model classes and the structure costs."""

import math

import numpy as np
import pytest

from body_scheme_core.learning.quality import (
    RANK_PENALTY,
    class_rank,
    model_cost,
    nesting_matrix,
    nests,
    prediction_errors,
    relative_complexity,
    replacement_cost,
)
from body_scheme_core.transforms import transform_from_rotvec


def test_prediction_errors_of_known_offsets():
    """A 0.1 m shift and a 0.3 rad rotation give exactly those errors."""
    Z = transform_from_rotvec([0.0, 0.0, 0.0], [1.0, 2.0, 3.0])
    Z2 = transform_from_rotvec([0.0, 0.3, 0.0], [1.0, 2.1, 3.0])
    e_t, e_r = prediction_errors(np.stack([Z, Z]), np.stack([Z, Z2]))
    np.testing.assert_allclose(e_t, [0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(e_r, [0.0, 0.3], atol=1e-7)


def test_model_cost_layers_never_overlap():
    """Any valid model of a lower (relative) complexity costs less than any of a higher one (paper Eq. 7, 12)."""
    rng = np.random.default_rng(0)
    ratios = rng.uniform(0.0, 1.0, size=(1000, 2))
    ratios[0] = [math.nextafter(1.0, 0.0)] * 2  # the worst valid model
    for layer in range(3):
        cost = model_cost(np.full(1000, layer), ratios[:, 0], ratios[:, 1])
        assert np.all(cost >= layer)
        assert np.all(cost < layer + 1)
    assert model_cost(0, 0.999999999, 0.999999999) < model_cost(1, 0.0, 0.0)


def test_relative_complexity_is_symmetric_difference():
    """C(M2|M1) counts actions added plus actions removed (paper Eq. 11)."""
    assert relative_complexity((1, 2), (1, 2)) == 0
    assert relative_complexity((), (5,)) == 1
    assert relative_complexity((1, 3), (1, 2)) == 2
    assert replacement_cost((5,), (5,), 0.2, 0.4) == pytest.approx(0.3 / (1.0 + 2 * RANK_PENALTY))
    assert replacement_cost((), (5,), 0.0, 0.0) == pytest.approx(1.0)


def test_classes_are_ordered_within_a_layer_by_error_plus_a_rank_penalty():
    """Rigid joints before GPs unless the GP predicts clearly better; layers never overlap (paper Eq. 7)."""
    revolute, gp = class_rank("revolute"), class_rank("gp")
    assert model_cost(1, 0.5, 0.5, revolute) < model_cost(1, 0.45, 0.45, gp)  # GP better, but not by the penalty
    assert model_cost(1, 0.5, 0.5, revolute) > model_cost(1, 0.2, 0.2, gp)  # GP far better
    assert model_cost(1, 0.99, 0.99, gp) < model_cost(2, 0.0, 0.0, class_rank("static")) == 2.0
    assert model_cost(1, 1.0, 1.0, gp) < 2.0
    assert class_rank("static") == class_rank("prismatic") < revolute < gp


def test_nesting_follows_flexibility_and_actions():
    """A GP on (a1, a2) nests a revolute joint on a1; a revolute joint never nests a prismatic one."""
    assert nests("gp", (1, 2), "revolute", (1,))
    assert nests("gp", (1,), "revolute", (1,))
    assert nests("revolute", (1,), "static", ())
    assert nests("gp", (1, 2), "gp", (1,))
    assert not nests("gp", (1,), "gp", (1,))
    assert not nests("revolute", (1,), "prismatic", (1,))
    assert not nests("gp", (2,), "revolute", (1,))
    assert not nests("engineered", (1,), "static", ())
    # A chain holds a joint of each of its actions; a GP of as many actions any smooth relation.
    assert nests("chain", (1, 2, 3), "revolute", (2,)) and nests("chain", (1, 2, 3), "chain", (1, 3))
    assert nests("gp", (1, 2, 3), "chain", (1, 2, 3)) and nests("chain", (1, 2, 3), "gp", (1, 3))
    assert not nests("chain", (1, 2), "gp", (1, 2)) and not nests("chain", (1, 2), "chain", (1, 2))
    assert not nests("chain", (1, 2), "revolute", (3,))


def test_a_chain_covers_the_actions_found_not_to_move_its_child_only_as_the_nesting_model():
    """A chain of a0..a2 that found a3 inert nests a GP of a0 and the inert a3 (a dummy action fitted to noise), but
    a chain that lacks a3 for that reason is nested by one of a0..a3, never the other way round."""
    kinds = ["chain", "gp", "chain"]
    actions = [(0, 1, 2), (0, 3), (0, 1, 2, 3)]
    covers = [(0, 1, 2, 3), (0, 3), (0, 1, 2, 3)]
    M = nesting_matrix(kinds, actions, 4, covers)
    assert M[1, 0] and M[1, 2]  # the GP is nested by both chains
    assert M[0, 2] and not M[2, 0]  # the chain of a0..a2 by the one of a0..a3 only
    assert not nesting_matrix(kinds, actions, 4)[1, 0]  # without covers: no
