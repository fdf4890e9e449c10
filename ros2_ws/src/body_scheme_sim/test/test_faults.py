"""Fault schedules: parsing "step:kind:args" entries and applying them to a world."""

from __future__ import annotations

import numpy as np
import pytest

from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_sim.errors import FaultScheduleError
from body_scheme_sim.faults import apply_fault, parse_fault, parse_fault_schedule
from body_scheme_sim.world import SimWorld

EXAMPLE = ["150:block_joint:5:0.8", "250:repair", "300:deform_limb:joint6:0.1:0.785:0:0",
           "320:displace_marker:7:0.05:0:0:0:0:0.3"]


def test_example_schedule_parses_into_steps_and_arguments():
    """The documented example yields sorted steps with the arguments of the world's fault methods."""
    schedule = parse_fault_schedule(list(reversed(EXAMPLE)))
    assert [step for step, _ in schedule] == [150, 250, 300, 320]
    faults = [fault for _, fault in schedule]
    assert [f.kind for f in faults] == ["block_joint", "repair", "deform_limb", "displace_marker"]
    assert faults[0].params == {"action_index": 5, "angle": 0.8}
    assert faults[1].params == {"repair_kind": None}
    assert faults[2].params == {"joint_name": "joint6", "delta_length": 0.1, "delta_rotvec": (0.785, 0.0, 0.0)}
    np.testing.assert_allclose(faults[3].params["delta"], transform_from_rotvec([0, 0, 0.3], [0.05, 0, 0]))
    assert faults[3].text == EXAMPLE[3]


def test_optional_arguments():
    """block_joint without an angle holds the joint; deform_limb and displace_marker take short forms."""
    assert parse_fault("3:block_joint:1").params == {"action_index": 1, "angle": None}
    assert parse_fault("3:deform_limb:link2:-0.05").params["delta_rotvec"] == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(parse_fault("3:displace_marker:4:0:0.02:0").params["delta"][:3, 3], [0, 0.02, 0])
    assert parse_fault("9:repair:block_joint").params == {"repair_kind": "block_joint"}


@pytest.mark.parametrize("entry, message", [
    ("x:repair", "step 'x' is not an integer"),
    ("block_joint:5", "unknown kind '5'"),
    ("-1:repair", "step must be >= 0"),
    ("5:explode", "unknown kind 'explode'"),
    ("5:block_joint", r"has 0 argument\(s\); expected STEP:block_joint:ACTION\[:ANGLE\]"),
    ("5:block_joint:x:0.1", "ACTION 'x' is not an integer"),
    ("5:deform_limb:joint6:0.1:0.7", "deform_limb:JOINT:DLENGTH"),
    ("5:displace_marker:7:0.05:nan:0", "finite"),
    ("5:displace_marker:7:a:0:0", "not all numbers"),
    ("5:repair:everything", "cannot repair 'everything'"),
    ("5", "at least STEP:KIND"),
])
def test_malformed_entries_raise_clear_errors(entry, message):
    """Each malformed entry names itself, the problem and the expected form."""
    with pytest.raises(FaultScheduleError, match=message):
        parse_fault(entry)


def test_a_string_instead_of_a_list_is_refused():
    """A bare string (a common YAML slip) is not parsed character by character."""
    with pytest.raises(FaultScheduleError, match="list of entries"):
        parse_fault_schedule("150:repair")


def test_scheduled_faults_apply_to_a_world_and_repair_restores_it():
    """Calling each parsed fault changes the world as its kind says; the repair entry undoes all."""
    with SimWorld("powercube_6dof", marker_texture=False) as world:
        world.execute([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
        before = world.true_marker_poses()
        for _, fault in parse_fault_schedule(EXAMPLE[2:] + ["400:block_joint:0:0.5"]):
            fault(world)
        assert [f["kind"] for f in world.faults] == ["deform_limb", "displace_marker", "block_joint"]
        assert world.joint_positions()[0] == 0.5
        assert not np.allclose(world.true_marker_poses()[7], before[7])
        parse_fault("0:repair")(world)
        assert world.faults == []
        for marker_id, pose in world.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])
        with pytest.raises(FaultScheduleError, match="unknown fault kind"):
            apply_fault(world, "melt")
