"""The ``body-scheme`` command's formatting and argument handling, and the nodes' refusal of run-time parameter
changes, without DDS traffic (the commands over DDS: tests/test_system_cli.py)."""

import array
import math

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.parameter import Parameter

from body_scheme_msgs.msg import SchemeEvent
from body_scheme_nodes import cli
from body_scheme_nodes.ros_parameters import refuse_parameter_changes


def test_a_status_reads_as_level_name_message_then_its_values():
    status = DiagnosticStatus(level=DiagnosticStatus.ERROR, name="/scheme_node: local model 1->2", message="mismatch",
                              values=[KeyValue(key="trans_error", value="0.031")])
    assert cli.format_status(status) == ["ERROR /scheme_node: local model 1->2: mismatch", "      trans_error: 0.031"]
    assert cli.format_status(status, values=False) == ["ERROR /scheme_node: local model 1->2: mismatch"]
    assert cli.format_status(DiagnosticStatus(level=DiagnosticStatus.STALE, name="x"))[0] == "STALE x: "


def test_an_event_reads_as_step_kind_edge_errors_and_reason():
    event = SchemeEvent(step=812, kind="model_replaced", reason="gp fits", parent_id=1, child_id=2,
                        model="gp(1->2 | a0)", trans_error=0.0123, rot_error=math.radians(2.5))
    assert cli.format_event(event) == ("step 812 model_replaced 1->2 (gp(1->2 | a0)) error 12.3 mm 2.5 deg: "
                                       "gp fits")
    bare = SchemeEvent(step=3, kind="structure_found", reason="", parent_id=-1, child_id=-1,
                       trans_error=math.nan, rot_error=math.nan)
    assert cli.format_event(bare) == "step 3 structure_found"


@pytest.mark.parametrize("text, value", [("0.5", 0.5), ("3", 3), ("true", True), ("[1, 2]", [1, 2]),
                                         ("abc", "abc"), ("[a, b]", ["a", "b"]), ("{bad", "{bad"),
                                         ("", ""), ("null", "null"), ("{a: 1}", "{a: 1}"), ("[1, 2.5]", "[1, 2.5]")])
def test_a_value_is_read_as_ros2_param_set_reads_it(text, value):
    assert cli.parse_value(text) == value


def test_a_node_name_may_lack_its_leading_slash():
    assert cli.full_name("scheme_node") == cli.full_name("/scheme_node") == "/scheme_node"
    assert cli.events_topic("/scheme_node") == "/body_scheme/events"
    assert cli.events_topic("/robot2/scheme_node") == "/robot2/body_scheme/events"
    assert cli.parser().parse_args(["events", "--node", "robot2/scheme_node"]).node == "/robot2/scheme_node"
    assert cli.parser().parse_args(["params", "babble_node"]).target == "/babble_node"
    assert cli.parser().parse_args(["status", "--node", "scheme_node"]).node == "/scheme_node"


def test_a_list_parameter_prints_as_a_list_whatever_its_container():
    assert cli.format_parameter_value([1, 2]) == cli.format_parameter_value(array.array("q", [1, 2])) == "[1, 2]"
    assert cli.format_parameter_value(0.5) == "0.5"


def test_a_wrong_command_line_exits_2_before_any_ros(capsys):
    for argv in ([], ["nonsense"], ["params"], ["save", "a", "b"]):
        with pytest.raises(SystemExit) as exited:
            cli.main(argv)
        assert exited.value.code == 2, argv
    assert cli.main(["status", "--timeout", "0"]) == 2
    assert "--timeout must be positive" in capsys.readouterr().err


def test_a_node_refuses_a_parameter_change_with_the_reason(context):
    node = rclpy.create_node("some_node", context=context)
    try:
        node.declare_parameter("rate", 1.0)
        refuse_parameter_changes(node)
        result = node.set_parameters([Parameter("rate", value=2.0)])[0]
        assert not result.successful and result.reason == "rate: read at start-up only; restart some_node to change it"
        assert node.get_parameter("rate").value == 1.0
        assert not node.set_parameters([Parameter("use_sim_time", value=True)])[0].successful  # times kept on its clock
        assert not node.get_clock().ros_time_is_active
    finally:
        node.destroy_node()
