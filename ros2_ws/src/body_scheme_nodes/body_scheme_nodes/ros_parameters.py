"""ROS parameter helpers shared by the nodes (no simulator: a real robot's nodes import this)."""

from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult

from body_scheme_core.errors import InvalidInputError

__all__ = ["declare_list_parameter", "refuse_parameter_changes"]


def declare_list_parameter(node, name, item_type):
    """Declare a list parameter whose default is empty and return its value as a list of ``item_type``.

    ROS cannot type an empty list (rclpy would call ``[]`` a byte array and refuse a later string list), so the
    parameter is dynamically typed and checked here.
    """
    value = node.declare_parameter(name, [], ParameterDescriptor(dynamic_typing=True)).value
    if value is None:  # "[]" in a parameter file
        return []
    if isinstance(value, (str, bytes)) or not all(isinstance(v, item_type) and not isinstance(v, bool)
                                                  for v in value):
        raise InvalidInputError(f"parameter {name} must be a list of {item_type.__name__}, got {value!r}")
    return list(value)


def refuse_parameter_changes(node):
    """Refuse every later parameter change, with the reason: our nodes read their parameters once at start-up, so
    a change accepted at run time would silently not apply (``body-scheme params NODE NAME VALUE`` prints the
    reason). ``use_sim_time`` too: its node keeps times of the clock it started with (receipt ages, the pairer's
    stamps, watchdogs), and with no ``/clock`` its timers would stop."""

    def refuse(parameters):
        names = ", ".join(p.name for p in parameters)
        return SetParametersResult(successful=False,
                                   reason=f"{names}: read at start-up only; restart {node.get_name()} to change it")

    node.add_on_set_parameters_callback(refuse)
