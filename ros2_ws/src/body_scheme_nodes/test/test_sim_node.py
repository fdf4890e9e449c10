"""sim_node's parameters and its message mapping (in-process; the DDS behaviour is in tests/)."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest
import rclpy
import yaml
from rclpy.parameter import Parameter

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import transform_from_xyz_rpy
from body_scheme_msgs.srv import InjectFault
from body_scheme_nodes import conversions
from body_scheme_nodes.sim_node import SimNode
from body_scheme_sim.camera import Camera

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config" / "sim_node.yaml"
BUILT_IN = {"use_sim_time", "start_type_description_service"}  # declared by rclpy itself


def flatten(tree, prefix=""):
    """Nested YAML parameters as ``{"camera.fx": value, ...}``."""
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


def declared_parameters(overrides=()):
    """Create a SimNode with ``overrides`` in a fresh rclpy context; return its parameters and the node's world."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = SimNode(context=context, parameter_overrides=list(overrides))
        try:
            names = [n for n in node.list_parameters([], 10).names if n not in BUILT_IN]
            return {p.name: p.value for p in node.get_parameters(names)}, node.world.camera
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_yaml_holds_every_parameter_at_its_declared_default():
    """config/sim_node.yaml lists exactly the declared parameters, each at its default and of its type."""
    declared, camera = declared_parameters()
    in_yaml = flatten(yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"])
    assert set(in_yaml) == set(declared)
    for name, value in in_yaml.items():
        default = declared[name] if declared[name] is not None else []  # typed empty lists are "not set"
        assert value == pytest.approx(list(default) if isinstance(default, (list, tuple)) else default), name
        assert type(value) is type(list(default) if isinstance(default, (list, tuple)) else default), name
    np.testing.assert_allclose(camera.world2camera, Camera().world2camera, atol=1e-12)


def test_camera_parameters_build_the_camera():
    """Intrinsics and the xyz + rpy pose of the parameters make the world's camera."""
    overrides = [Parameter("camera.width", value=320), Parameter("camera.fx", value=300.0),
                 Parameter("camera.xyz", value=[1.0, 0.5, 2.0]), Parameter("camera.rpy", value=[3.0, 0.1, 1.2]),
                 Parameter("perception_mode", value="noise")]
    _, camera = declared_parameters(overrides)
    assert camera.width == 320 and camera.fx == 300.0
    np.testing.assert_allclose(camera.world2camera, transform_from_xyz_rpy([1.0, 0.5, 2.0], [3.0, 0.1, 1.2]))


@pytest.mark.parametrize("name, value, message", [
    ("perception_mode", "magic", "perception_mode"), ("robot", "no_robot", "unknown robot"),
    ("fault_schedule", ["5:explode"], "unknown kind"), ("markers_of_interest", [1, 99], "markers_of_interest"),
    ("babbling_period", 0.0, "babbling_period"), ("visibility", 1.5, "visibility"),
    ("fault_schedule", [1, 2], "list of str"), ("max_in_flight", -1, "max_in_flight"),
    ("in_flight_timeout", 0.0, "in_flight_timeout")])
def test_bad_parameters_stop_the_node_with_a_reason(name, value, message):
    """Invalid settings raise at start-up naming the parameter or value."""
    with pytest.raises(InvalidInputError, match=message):
        declared_parameters([Parameter(name, value=value)])


def test_camera_info_message_carries_k_and_p():
    """CameraInfo has the size, K, P = [K | 0], no distortion."""
    K = Camera().K
    msg = conversions.camera_info_msg(12.5, "camera", 640, 480, K)
    assert (msg.width, msg.height, msg.header.frame_id) == (640, 480, "camera")
    np.testing.assert_array_equal(conversions.camera_from_info(msg)[0], K)
    np.testing.assert_array_equal(np.reshape(msg.p, (3, 4)), np.c_[K, np.zeros(3)])
    assert conversions.distortion_from_info(msg) is None
    assert conversions.seconds_from_stamp(msg.header.stamp) == 12.5


def test_joint_state_command_round_trip():
    """joint_state_msg is the inverse of actions_from_joint_state."""
    msg = conversions.joint_state_msg(3.25, ["a", "b"], [0.5, -1.0])
    stamp, actions = conversions.actions_from_joint_state(msg, ["b", "a"])
    assert stamp == 3.25
    np.testing.assert_array_equal(actions, [-1.0, 0.5])
    with pytest.raises(InvalidInputError):
        conversions.joint_state_msg(0.0, ["a"], [1.0, 2.0])


def test_inject_fault_requests_map_to_fault_arguments():
    """Each InjectFault kind maps to a core Fault; NaN angle holds; bad requests are refused."""
    def fault(request):
        result = conversions.fault_from_request(request)
        return result.kind, result.params

    request = InjectFault.Request(kind="block_joint", action_index=2, angle=math.nan)
    assert fault(request) == ("block_joint", {"action_index": 2, "angle": None})
    request = InjectFault.Request(kind="deform_limb", joint_name="joint3", delta_length=0.05)
    request.delta = [0.0, 0.0, 0.0, 0.0, 0.4, 0.0]
    assert fault(request) == (
        "deform_limb", {"joint_or_link": "joint3", "delta_length": 0.05, "delta_rotvec": [0.0, 0.4, 0.0]})
    request = InjectFault.Request(kind="displace_marker", marker_id=7)
    request.delta = [0.05, 0.0, 0.0, 0.0, 0.0, 0.3]
    kind, params = fault(request)
    assert kind == "displace_marker" and params["marker_id"] == 7
    np.testing.assert_allclose(params["delta"][:3, 3], [0.05, 0.0, 0.0])
    assert fault(InjectFault.Request(kind="repair")) == ("repair", {"repair_kind": None})
    with pytest.raises(InvalidInputError, match="unknown fault kind"):
        conversions.fault_from_request(InjectFault.Request(kind="break"))
    request = InjectFault.Request(kind="deform_limb", joint_name="joint3")
    request.delta = [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]
    with pytest.raises(InvalidInputError, match="delta\\[0:3\\] must be zero"):
        conversions.fault_from_request(request)
