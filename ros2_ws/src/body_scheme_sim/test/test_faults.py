"""Core faults applied to the simulated world (SimWorld.apply): parsed schedule entries change it as their kinds say."""

from __future__ import annotations

import numpy as np
import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.world import Fault, parse_fault, parse_fault_schedule
from body_scheme_sim.world import SimWorld

EXAMPLE = ["150:block_joint:5:0.8", "250:repair", "300:deform_limb:joint6:0.1:0.785:0:0",
           "320:displace_marker:7:0.05:0:0:0:0:0.3"]


def test_scheduled_faults_apply_to_a_world_and_repair_restores_it():
    """Calling each parsed fault changes the world as its kind says; the repair entry undoes all."""
    with SimWorld("powercube_6dof", marker_texture=False) as world:
        world.execute([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
        before = world.true_marker_poses()
        for _, fault in parse_fault_schedule(EXAMPLE[2:] + ["400:block_joint:0:0.5"]):
            world.apply(fault)
        assert [f.kind for f in world.faults] == ["deform_limb", "displace_marker", "block_joint"]
        assert world.joint_positions()[0] == 0.5
        assert not np.allclose(world.true_marker_poses()[7], before[7])
        world.apply(parse_fault("0:repair")[1])
        assert world.faults == []
        for marker_id, pose in world.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])
        with pytest.raises(InvalidInputError, match="fault kind must be one of"):
            world.apply(Fault("melt"))
