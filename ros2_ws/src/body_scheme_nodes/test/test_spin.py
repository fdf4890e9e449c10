"""Tests of run_node, the main() shared by every node."""

from body_scheme_core.errors import InvalidInputError
from body_scheme_nodes.spin import run_node


class RefusingNode:
    """Stands for a node whose constructor rejects its parameters."""

    def __init__(self):
        raise InvalidInputError("part_ids must name at least two distinct parts")


def test_refused_parameters_give_exit_code_1():
    """A BodySchemeError at start-up is not a traceback: exit code 1, rclpy shut down again."""
    import rclpy

    assert run_node(RefusingNode, args=[]) == 1
    assert not rclpy.ok()


def test_a_broken_parameter_file_gives_exit_code_1_without_a_traceback(tmp_path):
    """rclpy.init's RCLError (a --params-file that is not YAML) was a traceback before issue 20."""
    import rclpy

    broken = tmp_path / "broken.yaml"
    broken.write_text("/**:\n  ros__parameters: [\n  part_ids: {")
    assert run_node(RefusingNode, args=["--ros-args", "--params-file", str(broken)]) == 1
    assert not rclpy.ok()
