"""Fault schedules: "step:kind:args" entries parsed into core Faults, and their entry texts."""

from __future__ import annotations

import numpy as np
import pytest

from body_scheme_core.errors import FaultScheduleError, InvalidInputError
from body_scheme_core.transforms import transform_from_rotvec
from body_scheme_core.world import (
    RANDOM_FAULTS,
    Body,
    Fault,
    Joint,
    KinematicTree,
    Marker,
    parse_fault,
    parse_fault_schedule,
    random_fault,
    zoo_robot,
)

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
    assert faults[2].params == {"joint_or_link": "joint6", "delta_length": 0.1, "delta_rotvec": (0.785, 0.0, 0.0)}
    np.testing.assert_allclose(faults[3].params["delta"], transform_from_rotvec([0, 0, 0.3], [0.05, 0, 0]))
    assert [f"{step}:{fault.entry}" for step, fault in schedule][:2] == ["150:block_joint:5:0.8", "250:repair"]
    assert schedule[3][1].entry == "displace_marker:7:0.05:0.0:0.0:0.0:0.0:0.3"


def test_optional_arguments():
    """block_joint without an angle holds the joint; deform_limb and displace_marker take short forms."""
    assert parse_fault("3:block_joint:1")[1].params == {"action_index": 1, "angle": None}
    assert parse_fault("3:deform_limb:link2:-0.05")[1].params["delta_rotvec"] == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(parse_fault("3:displace_marker:4:0:0.02:0")[1].params["delta"][:3, 3], [0, 0.02, 0])
    assert parse_fault("9:repair:block_joint")[1].params == {"repair_kind": "block_joint"}


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


def test_entries_round_trip_and_the_core_body_refuses_what_only_a_world_can_apply():
    """Fault.entry parses back to the same fault; a hold-in-place block and a partial repair need a SimWorld."""
    for text in ["150:block_joint:5:0.8", "9:block_joint:1", "3:deform_limb:joint6:0.1:0.785:0.0:0.0", "4:repair",
                 "5:repair:deform_limb"]:
        step, fault = parse_fault(text)
        assert f"{step}:{fault.entry}" == text
    with pytest.raises(Exception, match="where it is"):
        parse_fault("3:block_joint:1")[1].apply(None, None)
    with pytest.raises(Exception, match="fault history"):
        parse_fault("3:repair:block_joint")[1].apply(None, None)
    assert Fault("repair").apply("current", "original") == "original"


def test_random_faults_act_on_every_zoo_body_and_move_a_marker_by_their_size():
    """Every zoo body has something each fault kind can change, and the change moves some marker by about its size."""
    for seed in range(40):
        tree = zoo_robot(seed)
        A = np.random.default_rng(seed).uniform(tree.action_lower, tree.action_upper, (30, tree.n_actions))
        before = Body(tree).true_marker_array(A)
        for kind in RANDOM_FAULTS:
            fault = random_fault(tree, kind, np.random.default_rng(seed), 0.05)
            after = fault.apply(Body(tree), Body(tree)).true_marker_array(A)
            moved = np.linalg.norm(after[..., :3, 3] - before[..., :3, 3], axis=-1).max()
            assert moved > (0.049 if kind in ("move_marker", "add_tool") else 1e-3), (seed, kind)


def test_a_random_fault_of_an_unknown_kind_or_on_a_body_without_it_is_refused():
    tree = zoo_robot(0)
    with pytest.raises(InvalidInputError, match="kind must be one of"):
        random_fault(tree, "melt", np.random.default_rng(0), 0.05)
    frozen = KinematicTree([Joint("j", "fixed", "base", "tip", origin=np.eye(4))],
                           [Marker(1, "base", np.eye(4), 0.05), Marker(2, "tip", np.eye(4), 0.05)], root_link="base")
    with pytest.raises(InvalidInputError, match="no commanded joint"):
        random_fault(frozen, "block_joint", np.random.default_rng(0), 0.05)
