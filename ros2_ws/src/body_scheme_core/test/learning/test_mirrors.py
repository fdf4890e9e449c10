"""A learned mirror image undone: the watch over the flip check's corrections, the poses chosen again, the learner."""

import math

import numpy as np
import pytest

from body_scheme_core.errors import ModelFileError
from body_scheme_core.learning import learner_step
from body_scheme_core.learning.config import BodySchemeConfig
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.mirrors import MIRROR_BLOCK, MirrorWatch, decide_flips, rechosen_history, rechosen_poses
from body_scheme_core.transforms import mirror_about_ray, rotational_error, transform_from_rotvec
from body_scheme_core.world import is_true_tree, make_session, planar_2dof, zoo_robot


def test_a_part_mirrored_in_more_than_half_of_a_block_is_reported_once_per_block():
    watch = MirrorWatch()
    reported = []
    for k in range(MIRROR_BLOCK):
        reported += watch.record([1, 2], [1] if k <= MIRROR_BLOCK // 2 else [2] if k < MIRROR_BLOCK // 2 - 1 else [])
    assert reported == [1]  # part 1: 31 of 60; part 2: none
    assert watch.counts == {}  # both blocks ended
    for _ in range(MIRROR_BLOCK // 2):
        assert watch.record([1], [1]) == []  # a new block: half of it is not more than half
    for _ in range(MIRROR_BLOCK // 2):
        assert watch.record([1], []) == []
    assert watch.counts == {}


def test_the_watch_round_trips_and_refuses_impossible_counts():
    watch = MirrorWatch()
    watch.record([3, 5], [5])
    again = MirrorWatch.from_list(watch.to_list(), {3, 5})
    assert again.counts == {3: [1, 0], 5: [1, 1]}
    for bad in ([[9, 1, 0]], [[3, 2, 3]], [[3, MIRROR_BLOCK, 0]], [[3, 1]], "x"):
        with pytest.raises(ModelFileError):
            MirrorWatch.from_list(bad, {3, 5})


def test_poses_are_chosen_again_against_the_mirror_of_the_prediction():
    """The scheme predicts each part's mirror image: true poses (corrected into agreement with it before) and flips
    alike are chosen again, the stored pose nearer the mirror of the prediction wins."""
    rng = np.random.default_rng(3)
    true = np.stack([transform_from_rotvec(rng.normal(size=3), [0.3, -0.2, 1.5] + 0.1 * rng.normal(size=3))
                     for _ in range(20)])
    predicted = mirror_about_ray(true)  # the learned mirror
    flipped = rng.random(20) < 0.3
    stored = np.where(flipped[:, None, None], mirror_about_ray(true), true)
    poses, changed = rechosen_poses(predicted, stored)
    assert np.allclose(poses, true) and np.array_equal(changed, flipped)



def _poses(k, seed=3):
    rng = np.random.default_rng(seed)
    return np.stack([transform_from_rotvec(rng.normal(size=3), [0.3, -0.2, 1.5] + 0.1 * rng.normal(size=3))
                     for _ in range(k)])


def test_a_flip_is_taken_in_mirrored_where_the_position_is_explained_and_refused_where_not():
    true = _poses(3)
    far = mirror_about_ray(true[2])
    far[:3, 3] *= 1.3  # along the ray: the mirror image stays the same, the position is off
    given = {1: true[0], 2: mirror_about_ray(true[1]), 3: far, 4: true[0]}
    flips = decide_flips({1: true[0], 2: true[1], 3: true[2]}, given, math.radians(5), 0.05)
    assert flips.judged == [1, 2, 3] and flips.mirrored == [2] and [p for p, _ in flips.refused] == [3]
    assert np.allclose(flips.observations[2], true[1]) and set(flips.observations) == {1, 2, 4}
    assert np.array_equal(given[2], mirror_about_ray(true[1]))  # the input is not changed


def _nearly_face_on(tilt_deg):
    """A marker at 1.5 m whose normal is ``tilt_deg`` off the camera's ray: its mirror image is twice that away."""
    position = np.array([0.3, -0.2, 1.5])
    z = -position / np.linalg.norm(position)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = np.column_stack([x, np.cross(z, x), z]), position
    return pose @ transform_from_rotvec([math.radians(tilt_deg), 0.0, 0.0], [0.0, 0.0, 0.0])


def test_a_tracker_known_to_flip_has_its_flips_of_a_nearly_face_on_marker_taken_in_mirrored():
    true, theta = _nearly_face_on(1.5), math.radians(5)
    flip = mirror_about_ray(true)
    assert math.radians(2.9) < rotational_error(true[None], flip[None])[0] < math.radians(3.1)  # within theta
    noisy = true @ transform_from_rotvec([0.0, math.radians(2.5), 0.0], [0.0, 0.0, 0.0])  # a true pose, 2.5 deg off
    given = {1: flip, 2: noisy}
    assert decide_flips({1: true, 2: true}, given, theta, 0.05).mirrored == []  # off by less than theta: let through
    eager = decide_flips({1: true, 2: true}, given, theta, 0.05, eager=True)
    assert eager.mirrored == [1] and np.allclose(eager.observations[1], true)
    assert np.array_equal(eager.observations[2], noisy)  # its mirror image is no nearer: kept as given
    tiny = {1: mirror_about_ray(_nearly_face_on(0.4))}  # 0.8 deg: below EAGER_FLOOR * theta, noise
    assert decide_flips({1: _nearly_face_on(0.4)}, tiny, theta, 0.05, eager=True).mirrored == []


def test_a_history_chosen_again_changes_new_records_only_and_drops_the_other_solutions_covariance():
    true = _poses(4)
    # What a scheme holding part 7's mirror image kept: true poses corrected into its mirror, one pose left true.
    stored = [mirror_about_ray(true[0]), mirror_about_ray(true[1]), true[2], mirror_about_ray(true[3])]
    records = [(s, np.full(1, float(s)), {7: stored[s], 8: true[s]}) for s in range(4)]
    covariances = {0: {7: np.eye(6), 8: np.eye(6)}, 2: {7: np.eye(6)}}
    new, covs, changed, n = rechosen_history(records, covariances, 7,
                                             lambda A: mirror_about_ray(true[A[:, 0].astype(int)]))
    assert (changed, n) == (3, 4) and all(np.allclose(new[s][2][7], true[s]) for s in range(4))
    assert new[2] is records[2] and all(np.array_equal(new[s][2][8], true[s]) for s in range(4))
    assert set(covs[0]) == {8} and set(covs[2]) == {7} and set(covariances[0]) == {7, 8}
    assert records[0][2][7] is stored[0]

def test_a_learner_whose_scheme_holds_a_parts_mirror_chooses_its_stored_poses_again():
    """A calibrated learner is shown one part mirrored about the ray on every step (as a scheme holding the part's
    mirror sees its true poses): the flip check takes each in corrected until a block of them is over half corrected;
    then a ``mirror_undone`` event names the part and every stored pose of it is the one observed again."""
    robot = planar_2dof()
    session = make_session(robot, 160, seed=4, sigma_trans=0.005, sigma_rot=math.radians(1.0))
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions)
    for t in range(80):
        learner.update(session.actions[t], session.observations[t])
    assert learner.phase == "steady"
    part, events, given = 3, [], {}
    for t in range(80, 160):
        observations = dict(session.observations[t])
        observations[part] = given[t] = mirror_about_ray(observations[part])
        events += learner.update(session.actions[t], observations)
        if any(e.kind == "mirror_undone" for e in events):
            break
    undone = [e for e in events if e.kind == "mirror_undone"]
    assert len(undone) == 1 and undone[0].child == part and learner.corrected["flipped"] >= MIRROR_BLOCK // 2
    _, stored = learner.samples()
    for s, obs in zip(range(learner.step - len(stored), learner.step), stored, strict=True):  # one record a step
        if s in given and rotational_error(given[s][None], mirror_about_ray(given[s])[None])[0] > 0.1:
            assert np.allclose(obs[part], given[s])
    assert BodySchemeLearner.from_state(learner.to_state()).to_state() == learner.to_state()


@pytest.mark.parametrize("told", [False, True])
def test_the_learner_checks_flips_eagerly_only_when_told_its_tracker_flips(told, monkeypatch):
    """``mirror_hypotheses`` (a tracker known to flip) lowers the flip check's floor once the scheme is calibrated."""
    robot = planar_2dof()
    session = make_session(robot, 60, seed=4, sigma_trans=0.005, sigma_rot=math.radians(1.0))
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, BodySchemeConfig(mirror_hypotheses=told))
    seen = []
    monkeypatch.setattr(learner_step, "decide_flips",
                        lambda *args, **kwargs: seen.append(kwargs["eager"]) or decide_flips(*args, **kwargs))
    for t in range(60):
        learner.update(session.actions[t], session.observations[t])
    assert seen and set(seen) == {told}


@pytest.mark.heavy(seconds=20)
@pytest.mark.slow  # two 400-step zoo bodies, with and without the hypotheses
@pytest.mark.parametrize("seed", [24, 36])
def test_with_mirror_hypotheses_a_body_whose_poses_flip_often_is_learned_while_without_it_is_not(seed):
    """Two of the robot zoo's bodies at a tag tracker's noise with 30 % of the orientations mirrored from the first
    step: with ``mirror_hypotheses`` the learner has the true tree after 200 steps, without it none (its candidates'
    test windows hold the flips)."""
    tree = zoo_robot(seed)
    session = make_session(tree, 200, seed, visibility=0.85, sigma_trans=math.sqrt(2 * 0.003**2 + 0.020**2),
                           sigma_rot=math.radians(3.0), depth_ratio=0.020 / 0.003, flip_rate=0.30)
    learned = {}
    for on in (False, True):
        learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, BodySchemeConfig(mirror_hypotheses=on))
        for t in range(session.n_steps):
            learner.update(session.actions[t], session.observations[t])
        learned[on] = learner.body_scheme is not None and learner.phase != "bootstrapping" and is_true_tree(
            tree, learner.body_scheme)
    assert learned == {False: False, True: True}
