"""Motor babbling: uniform within the limits, no collisions, markers of interest visible."""

from __future__ import annotations

import math

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import transform_from_xyz_rpy
from body_scheme_core.world import Joint, KinematicTree, Marker, babble
from body_scheme_sim.babbling import babbling_screen
from body_scheme_sim.errors import BabblingError
from body_scheme_sim.world import SimWorld


def ground_hitting_arm():
    """One 0.5 m link pitching +-3 rad about y on a 0.2 m post: beyond about +-1.92 rad it is in the ground."""
    def offset(z):
        return transform_from_xyz_rpy((0.0, 0.0, z), (0.0, 0.0, 0.0))
    joints = [Joint("pitch", "revolute", "base", "arm", origin=offset(0.2), axis=(0.0, 1.0, 0.0), lower=-3.0,
                    upper=3.0, action=0),
              Joint("tip_joint", "fixed", "arm", "tip", origin=offset(0.5))]
    facing = transform_from_xyz_rpy((0.05, 0.0, 0.1), (0.0, math.pi / 2, 0.0))
    return KinematicTree(joints, [Marker(1, "base", facing), Marker(2, "arm", facing)])


def test_babbling_respects_the_joint_limits_and_is_reproducible():
    """Babbled commands lie within the limits, cover them, and repeat for the same seed."""
    with SimWorld("powercube_6dof", marker_texture=False) as world:
        A = babble(world, 60, np.random.default_rng(0), screen=babbling_screen(world))
        assert A.shape == (60, 6)
        assert np.all(A >= world.action_lower) and np.all(A <= world.action_upper)
        span = world.action_upper - world.action_lower
        assert np.all(A.max(axis=0) - A.min(axis=0) > 0.6 * span)
        first, again = (babble(world, 10, 0, screen=babbling_screen(world)) for _ in range(2))
        np.testing.assert_array_equal(first, again)


def test_babbling_rejects_collisions():
    """On an arm that hits the ground for a third of its range, no babbled command collides."""
    with SimWorld(ground_hitting_arm(), marker_texture=False) as world:
        A = babble(world, 40, np.random.default_rng(0), screen=babbling_screen(world))
        assert np.all(np.abs(A[:, 0]) < 1.95)  # uniform sampling without rejection would exceed it ~14 times
        for a in A:
            world.execute(a)
            assert not world.in_collision()
        world.execute([2.2])
        assert world.in_collision()


def test_babbling_keeps_markers_of_interest_visible():
    """Every babbled configuration shows the markers of interest; without them, some would not."""
    with SimWorld("powercube_6dof", marker_texture=False) as world:
        for a in babble(world, 15, np.random.default_rng(1), screen=babbling_screen(world, [6, 7])):
            world.execute(a)
            assert {6, 7} <= world.visible_marker_ids()
        hidden = 0
        for a in babble(world, 15, np.random.default_rng(1), screen=babbling_screen(world)):
            world.execute(a)
            hidden += not {6, 7} <= world.visible_marker_ids()
        assert hidden > 0


def test_babbling_leaves_the_world_as_it_was():
    """After babbling, the robot is back at its last command (blocked joints stay blocked)."""
    with SimWorld("arm_4dof", marker_texture=False) as world:
        world.execute([0.3, -0.2, 0.4, 0.1])
        world.block_joint(1, 0.5)
        before, q = world.true_marker_poses(), world.joint_positions()
        babble(world, 5, 0, screen=babbling_screen(world))
        np.testing.assert_array_equal(world.joint_positions(), q)
        for marker_id, pose in world.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])
        np.testing.assert_array_equal(world.last_command, [0.3, -0.2, 0.4, 0.1])


def test_babbling_gives_up_with_the_reasons():
    """If the markers of interest can never be seen together, babbling fails naming the counts."""
    with SimWorld(ground_hitting_arm(), marker_texture=False) as world:
        world.displace_marker(2, np.diag([-1.0, 1.0, -1.0, 1.0]))  # marker 2 now faces away from the camera
        with pytest.raises(BabblingError, match=r"0 of 3 valid configurations in 50 tries.*hidden"):
            babble(world, 3, 0, screen=babbling_screen(world, [2]), max_draws=50)
        with pytest.raises(InvalidInputError, match="not markers of the robot"):
            babble(world, 3, 0, screen=babbling_screen(world, [9]))
        with pytest.raises(InvalidInputError, match="n must be"):
            babble(world, -1, 0)
        assert babble(world, 0, 0, screen=babbling_screen(world)).shape == (0, 1)
