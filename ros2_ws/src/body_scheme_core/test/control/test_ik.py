"""Tests of solve_ik: convergence on reachable targets, honest failure, joint limits, restarts, frames."""

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from body_scheme_core.control.ik import IKResult, solve_ik, trained_bounds
from body_scheme_core.errors import InvalidInputError
from body_scheme_core.models.base import LocalModel
from body_scheme_core.models.gp import GPModel
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.prediction.uncertainty import error_radius, position_covariance
from body_scheme_core.transforms import invert_transform, transform_from_rotvec
from body_scheme_core.world import planar_2dof


def rot_z(angle, derivative=False):
    c, s = np.cos(angle), np.sin(angle)
    T = np.zeros((4, 4)) if derivative else np.eye(4)
    T[:2, :2] = [[-s, -c], [c, -s]] if derivative else [[c, -s], [s, c]]
    return T


class RevoluteModel(LocalModel):
    """Analytic test model ``parent2child(a) = A @ Rz(a_k) @ B`` (``A @ B`` without an action).

    The same as in test_scheme.py; repeated because pytest's importlib mode keeps test modules apart.
    """

    kind = "test_revolute"

    def __init__(self, parent, child, action=None, A=None, B=None):
        super().__init__(parent, child, () if action is None else (action,))
        self.A = np.eye(4) if A is None else np.asarray(A, dtype=float)
        self.B = np.eye(4) if B is None else np.asarray(B, dtype=float)

    is_fitted = True

    def fit(self, A, Z):
        return self

    def predict(self, A, return_std=False):
        q = self._select(A)
        Z = np.array([self.A @ rot_z(t) @ self.B for t in (q[:, 0] if self.actions else np.zeros(len(q)))])
        return (Z, np.zeros((len(Z), 2))) if return_std else Z

    def jacobian(self, a, eps=None):
        J = np.zeros((len(a), 4, 4))
        for k in self.actions:
            J[k] = self.A @ rot_z(a[k], derivative=True) @ self.B
        return J

    def to_dict(self):
        raise NotImplementedError

    @classmethod
    def from_dict(cls, data):
        raise NotImplementedError


def translation(x, y=0.0, z=0.0):
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def planar_arm():
    """2-DOF planar arm, links 1.0 m and 0.8 m, parts 10 (base) -> 20 -> 30 (tip), plus a static part 40."""
    models = [RevoluteModel(10, 20, 0, B=translation(1.0)),
              RevoluteModel(30, 20, 1, A=translation(-0.8)),  # stored tip->elbow: Z = Tx(-0.8) Rz(a1)
              RevoluteModel(10, 40, None, B=translation(0.0, 0.0, 0.3))]
    return BodyScheme((10, 20, 30, 40), 10, models)


def spatial_arm(rng, n_joints=6):
    """Chain of random revolute joints with random link transforms, parts 0..n_joints."""
    models = [RevoluteModel(j, j + 1, j, transform_from_rotvec(rng.normal(size=3), 0.2 * rng.normal(size=3)),
                            translation(0.0, 0.0, 0.25)) for j in range(n_joints)]
    return BodyScheme(tuple(range(n_joints + 1)), 0, models)


def test_reaches_reachable_targets():
    """Targets produced by the forward model from random actions are reached within tol."""
    rng = np.random.default_rng(0)
    scheme = spatial_arm(rng)
    lower, upper = -np.pi * np.ones(6), np.pi * np.ones(6)
    for _ in range(10):
        target = scheme.predict(rng.uniform(lower, upper))[6][:3, 3]
        result = solve_ik(scheme, 6, target, np.zeros(6), lower, upper, tol=1e-4)
        assert isinstance(result, IKResult)
        assert result.success, result.reason
        assert result.residual <= 1e-4
        assert np.linalg.norm(scheme.predict(result.actions)[6][:3, 3] - target) <= 1e-4
        assert_allclose(result.position, target, atol=1e-4)
        assert result.reason.startswith("converged")


def test_unreachable_target_reports_failure():
    """A target 5 m away is reported unreachable with the best residual, never as success."""
    scheme = planar_arm()
    result = solve_ik(scheme, 30, [5.0, 0.5, 0.0], [0.3, 0.4], -np.pi, np.pi, n_restarts=2)
    assert not result.success
    assert result.reason.startswith("target unreachable")
    assert "after 2 restarts" in result.reason
    # The best the arm can do is to stretch towards the target: 1.8 m reach.
    assert result.residual == pytest.approx(np.hypot(5.0, 0.5) - 1.8, abs=1e-3)
    assert f"{result.residual:.3g}" in result.reason


def test_joint_limits_are_respected():
    """Results stay within the limits; a target reachable only outside them is reported as failure."""
    scheme = planar_arm()
    lower, upper = np.array([-0.5, -0.5]), np.array([0.5, 0.5])
    inside = scheme.predict([0.4, -0.3])[30][:3, 3]
    result = solve_ik(scheme, 30, inside, [0.0, 0.0], lower, upper)
    assert result.success, result.reason
    assert np.all(result.actions >= lower) and np.all(result.actions <= upper)
    outside = scheme.predict([2.0, 1.0])[30][:3, 3]
    result = solve_ik(scheme, 30, outside, [0.0, 0.2], lower, upper)
    assert not result.success
    assert np.all(result.actions >= lower) and np.all(result.actions <= upper)
    # The closest point within the box is at the corner of joint 0's limit.
    assert result.actions[0] == pytest.approx(0.5)


def test_start_outside_limits_is_clipped():
    """An a0 outside the limits is clipped before the search; the result respects the limits."""
    scheme = planar_arm()
    target = scheme.predict([0.2, 0.3])[30][:3, 3]
    result = solve_ik(scheme, 30, target, [3.0, -3.0], [-1.0, -1.0], [1.0, 1.0])
    assert result.success, result.reason
    assert np.all(np.abs(result.actions) <= 1.0)


def test_only_influencing_actions_change():
    """Actions outside the part's path and fixed actions (lower == upper) keep their start value."""
    scheme = planar_arm()
    a0 = np.array([0.1, 0.2, 0.7])  # a2 influences nothing
    target = scheme.predict([0.9, 0.5])[20][:3, 3]
    result = solve_ik(scheme, 20, target, a0, -np.pi, np.pi)  # part 20 depends on a0 only
    assert result.success, result.reason
    assert_array_equal(result.actions[1:], a0[1:])
    # Joint 0 fixed: only joint 1 moves, so the tip reaches targets on the circle around the elbow.
    lower, upper = np.array([0.3, -np.pi, 0.0]), np.array([0.3, np.pi, 0.0])
    target = scheme.predict([0.3, -1.2, 0.0])[30][:3, 3]
    result = solve_ik(scheme, 30, target, [0.3, 0.0, 0.0], lower, upper)
    assert result.success, result.reason
    assert result.actions[0] == 0.3 and result.actions[2] == 0.0


def test_restart_escapes_a_stuck_start():
    """From the stretched (singular) pose the gradient towards a target on the arm's axis vanishes; a restart helps."""
    scheme = planar_arm()
    # Analytic derivatives keep the singularity exact (forward differences' O(h) term can break the symmetry).
    result = solve_ik(scheme, 30, [1.2, 0.0, 0.0], [0.0, 0.0], -np.pi, np.pi, n_restarts=3, derivatives="analytic")
    assert result.success, result.reason
    assert result.restarts >= 1
    stuck = solve_ik(scheme, 30, [1.2, 0.0, 0.0], [0.0, 0.0], -np.pi, np.pi, n_restarts=0, derivatives="analytic")
    assert not stuck.success
    assert stuck.reason.startswith("target unreachable")
    assert stuck.restarts == 0


def test_forward_and_analytic_derivatives_agree():
    """Both derivative modes reach the same solution from the same start."""
    rng = np.random.default_rng(0)
    scheme = spatial_arm(rng)
    for _ in range(3):
        target = scheme.predict(rng.uniform(-np.pi, np.pi, size=6))[6][:3, 3]
        a0 = rng.uniform(-1.0, 1.0, size=6)
        fwd = solve_ik(scheme, 6, target, a0, -np.pi, np.pi, tol=1e-6, derivatives="forward")
        ana = solve_ik(scheme, 6, target, a0, -np.pi, np.pi, tol=1e-6, derivatives="analytic")
        assert fwd.success and ana.success
        if fwd.restarts == ana.restarts == 0:
            assert_allclose(fwd.actions, ana.actions, atol=1e-4)


def test_max_iterations_reported():
    """A too small iteration budget yields 'max iterations reached', not success."""
    rng = np.random.default_rng(0)
    scheme = spatial_arm(rng)
    target = scheme.predict(rng.uniform(-np.pi, np.pi, size=6))[6][:3, 3]
    result = solve_ik(scheme, 6, target, np.zeros(6), -np.pi, np.pi, tol=1e-9, max_iterations=1, n_restarts=0)
    assert not result.success
    assert result.reason.startswith("max iterations reached")
    assert result.iterations == 1


def test_part_not_in_scheme_and_static_part():
    """Unknown parts and parts no action moves give success=False with a reason; a static part already there is ok."""
    scheme = planar_arm()
    result = solve_ik(scheme, 99, [1.0, 0.0, 0.0], [0.0, 0.0], -1.0, 1.0)
    assert not result.success and result.reason.startswith("part not in body scheme")
    result = solve_ik(scheme, 40, [1.0, 0.0, 0.0], [0.0, 0.0], -1.0, 1.0)
    assert not result.success and result.reason.startswith("no action influences part")
    assert result.residual == pytest.approx(np.hypot(1.0, 0.3))
    result = solve_ik(scheme, 40, [0.0, 0.0, 0.3], [0.0, 0.0], -1.0, 1.0)
    assert result.success


def test_target_in_world_frame():
    """With world2root the target is given in world coordinates."""
    scheme = planar_arm()
    world2root = transform_from_rotvec([0.0, 0.0, 0.7], [2.0, -1.0, 0.5])
    a_true = np.array([0.6, -0.9])
    target_world = (world2root @ scheme.predict(a_true)[30])[:3, 3]
    result = solve_ik(scheme, 30, target_world, [0.0, 0.3], -np.pi, np.pi, world2root=world2root)
    assert result.success, result.reason
    assert_allclose((invert_transform(world2root) @ np.append(target_world, 1.0))[:3], result.position, atol=1e-3)


@pytest.mark.parametrize("kwargs, match", [
    ({"a0": np.zeros((1, 2))}, "a0"),
    ({"lower": np.zeros(3)}, "lower"),
    ({"lower": 1.0, "upper": 0.0}, "exceed"),
    ({"target_position": [1.0, 0.0]}, "target_position"),
    ({"tol": 0.0}, "tol"),
    ({"max_iterations": 0}, "max_iterations"),
    ({"n_restarts": -1}, "n_restarts"),
    ({"world2root": np.ones((4, 4))}, "world2root"),
    ({"derivatives": "central"}, "derivatives"),
])
def test_bad_input_is_rejected(kwargs, match):
    """Malformed arguments raise InvalidInputError naming the argument."""
    args = {"a0": np.zeros(2), "lower": -1.0, "upper": 1.0, "target_position": [1.0, 0.0, 0.0]}
    args.update(kwargs)
    with pytest.raises(InvalidInputError, match=match):
        solve_ik(planar_arm(), 30, args.pop("target_position"), args.pop("a0"), args.pop("lower"),
                 args.pop("upper"), **args)


def learned_planar_arm(rng):
    """GP scheme of the paper's 2-DOF arm, each model fitted on 30 noise-free samples of the true transforms."""
    tree = planar_2dof()
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(30, tree.n_actions))
    models = [GPModel(p, c, tree.path_actions(p, c)).fit(A, tree.relative_transform(p, c, A))
              for p, c in tree.marker_tree_edges()]
    return tree, BodyScheme(tree.marker_ids, tree.root_marker, models)


def test_ik_on_learned_arm_reaches_reachable_targets():
    """On a GP-learned 2-DOF arm, IK reaches targets within tol and the true arm lands near them."""
    rng = np.random.default_rng(0)
    tree, scheme = learned_planar_arm(rng)
    lower, upper = tree.action_lower, tree.action_upper
    for _ in range(10):
        a_true = rng.uniform(lower, upper)
        target = tree.relative_transform(1, 3, a_true)[:3, 3]
        # Targets the learned model can reach exactly: its own prediction; the true arm's pose is within model error.
        learned_target = scheme.predict(a_true)[3][:3, 3]
        result = solve_ik(scheme, 3, learned_target, np.zeros(2), lower, upper, tol=1e-3, confidence=0.0)
        assert result.success and result.converged, result.reason
        assert result.residual <= 1e-3
        assert np.all(result.actions >= lower) and np.all(result.actions <= upper)
        reached = tree.relative_transform(1, 3, result.actions)[:3, 3]
        assert np.linalg.norm(reached - target) < np.linalg.norm(learned_target - target) + 0.05


def test_success_needs_the_predicted_error_bound_within_the_tolerance():
    """On the GP arm the model reaches a target to 1 mm, but its predicted position is uncertain by centimetres: not
    a success, and the reason says so; the bound is the residual plus the radius holding the predicted position's
    error at the two-sigma level (95.4 %); with confidence 0 the
    model's word suffices. On exact (engineered) models the uncertainty is zero and nothing changes."""
    rng = np.random.default_rng(0)
    tree, scheme = learned_planar_arm(rng)
    target = scheme.predict(np.array([0.4, -0.3]))[3][:3, 3]
    result = solve_ik(scheme, 3, target, np.zeros(2), tree.action_lower, tree.action_upper, tol=1e-3)
    assert result.converged and not result.success and result.reason.startswith("not sure enough")
    assert result.position_std > 1e-3
    cov = position_covariance(scheme, result.actions, 3)
    assert result.error_bound == pytest.approx(result.residual + error_radius(cov, 2.0))
    assert result.position_std == pytest.approx(np.sqrt(np.trace(cov)))
    loose = solve_ik(scheme, 3, target, np.zeros(2), tree.action_lower, tree.action_upper, tol=1e-3,
                     confidence=0.0)
    assert loose.success and loose.error_bound == pytest.approx(loose.residual)
    exact = solve_ik(planar_arm(), 30, [0.3, 0.2, 0.0], np.zeros(2), -np.pi, np.pi)
    assert exact.success and exact.position_std == 0.0


def test_the_error_bound_covers_where_the_true_arm_goes():
    """Over 40 random targets the true arm's part lands within the reported bound (two-sigma level) of the
    target for at least 90 % of them: the uncertainty is not overconfident."""
    rng = np.random.default_rng(1)
    tree, scheme = learned_planar_arm(rng)
    covered = []
    for a in rng.uniform(tree.action_lower, tree.action_upper, size=(40, 2)):
        target = tree.relative_transform(1, 3, a)[:3, 3]
        result = solve_ik(scheme, 3, target, np.zeros(2), tree.action_lower, tree.action_upper)
        covered.append(np.linalg.norm(tree.relative_transform(1, 3, result.actions)[:3, 3] - target)
                       <= result.error_bound)
    assert np.mean(covered) >= 0.9


def test_prefer_certain_returns_the_least_uncertain_solution():
    """With every restart used, the solution returned never has a larger error bound than the first one found (the
    bound is what success needs; at confidence 0, the std), and for some targets (the 2-DOF arm's elbow-up and
    elbow-down solutions) it is the other, surer one."""
    rng = np.random.default_rng(2)
    tree, scheme = learned_planar_arm(rng)
    better = 0
    for a in rng.uniform(tree.action_lower, tree.action_upper, size=(10, 2)):
        target = scheme.predict(a)[3][:3, 3]
        first = solve_ik(scheme, 3, target, np.zeros(2), tree.action_lower, tree.action_upper, rng=1)
        certain = solve_ik(scheme, 3, target, np.zeros(2), tree.action_lower, tree.action_upper, rng=1,
                           prefer_certain=True, n_restarts=8)
        assert certain.converged and certain.error_bound <= first.error_bound + 1e-12
        better += certain.error_bound < first.error_bound - 1e-4
        limits = (np.zeros(2), tree.action_lower, tree.action_upper)
        first0 = solve_ik(scheme, 3, target, *limits, rng=1, confidence=0.0)
        plain = solve_ik(scheme, 3, target, *limits, rng=1, prefer_certain=True, n_restarts=8, confidence=0.0)
        assert plain.position_std <= first0.position_std + 1e-12
    assert better >= 1


def test_ik_on_learned_arm_reports_unreachable_target():
    """A target 5 m away from the learned 2-DOF arm is reported as unreachable, with actions within limits."""
    rng = np.random.default_rng(0)
    tree, scheme = learned_planar_arm(rng)
    lower, upper = tree.action_lower, tree.action_upper
    result = solve_ik(scheme, 3, [5.0, 0.0, 0.1], np.zeros(2), lower, upper)
    assert not result.success
    assert result.reason.startswith("target unreachable")
    assert result.residual > 4.0
    assert np.all(result.actions >= lower) and np.all(result.actions <= upper)


def test_trained_bounds_shrink_limits_to_the_training_inputs_of_learned_models():
    """Each action's limits shrink to the training range of the GPs depending on it; analytic models keep limits."""
    tree = planar_2dof()
    rng = np.random.default_rng(0)
    A = np.column_stack([rng.uniform(-0.5, 0.3, 40), rng.uniform(-1.0, 1.0, 40)])  # a0 seen only in [-0.5, 0.3]
    gp = GPModel(1, 2, (0,)).fit(A, tree.relative_transform(1, 2, A))
    low, high = gp.training_range()
    assert_allclose([low[0], high[0]], [A[:, 0].min(), A[:, 0].max()])
    scheme = BodyScheme((1, 2, 3), 1, [gp, RevoluteModel(2, 3, 1, B=translation(0.4))])
    lower, upper = trained_bounds(scheme, [-2.0, -2.0], [2.0, 2.0])
    assert_allclose(lower, [A[:, 0].min(), -2.0])
    assert_allclose(upper, [A[:, 0].max(), 2.0])
    # Limits tighter than the training range win; disjoint ones collapse onto the range's nearest end.
    lower, upper = trained_bounds(scheme, [0.0, -1.0], [1.0, 1.0])
    assert_allclose([lower[0], upper[0]], [0.0, A[:, 0].max()])
    lower, upper = trained_bounds(scheme, [1.0, -1.0], [2.0, 1.0])
    assert_allclose([lower[0], upper[0]], [A[:, 0].max(), A[:, 0].max()])
    with pytest.raises(InvalidInputError, match="vectors of one length"):
        trained_bounds(scheme, [0.0], [1.0, 1.0])


def test_ik_within_trained_bounds_avoids_where_the_learned_model_only_guesses():
    """With one arm configuration never observed, IK in the trained range lands the true arm nearer the target."""
    tree = planar_2dof()
    rng = np.random.default_rng(1)
    lower, upper = tree.action_lower, tree.action_upper
    A = np.column_stack([rng.uniform(lower[0], upper[0], 60), rng.uniform(lower[1], 0.0, 60)])  # a1 > 0 unseen
    models = [GPModel(p, c, tree.path_actions(p, c)).fit(A, tree.relative_transform(p, c, A))
              for p, c in tree.marker_tree_edges()]
    scheme = BodyScheme(tree.marker_ids, tree.root_marker, models)
    errors = {"limits": [], "trained": []}
    for _ in range(10):
        a_true = np.array([rng.uniform(lower[0], upper[0]), rng.uniform(lower[1], 0.0)])  # reachable with a1 <= 0
        target = tree.relative_transform(1, 3, a_true)[:3, 3]
        for name, (lo, hi) in (("limits", (lower, upper)), ("trained", trained_bounds(scheme, lower, upper))):
            result = solve_ik(scheme, 3, target, np.array([0.0, upper[1]]), lo, hi, tol=1e-3)
            errors[name].append(np.linalg.norm(tree.relative_transform(1, 3, result.actions)[:3, 3] - target))
    assert np.max(errors["trained"]) < 0.05
    assert np.max(errors["trained"]) < 0.5 * np.max(errors["limits"])
