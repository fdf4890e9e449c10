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


def test_a_bad_thread_count_gives_exit_code_1_before_rclpy_starts(monkeypatch):
    """BODY_SCHEME_MATH_THREADS that is not a positive integer: one FATAL line, exit code 1."""
    import rclpy

    monkeypatch.setenv("BODY_SCHEME_MATH_THREADS", "many")
    assert run_node(RefusingNode, args=[]) == 1
    assert not rclpy.ok()


def test_a_node_is_built_with_one_math_thread(monkeypatch):
    """run_node limits the BLAS pools before the node's constructor runs (which may restore and fit a checkpoint)."""
    import numpy  # noqa: F401  (its BLAS pool, one thread per core until limited)
    from threadpoolctl import threadpool_info, threadpool_limits

    from body_scheme_core.threads import MATH_THREAD_VARIABLES

    monkeypatch.delenv("BODY_SCHEME_MATH_THREADS", raising=False)
    for name in MATH_THREAD_VARIABLES:  # run_node sets them: monkeypatch puts them back after the test
        monkeypatch.setenv(name, "2")
    threadpool_limits(limits=2)  # as numpy starts on two cores (an earlier test in this process may have limited it)
    seen = []

    class CountingNode(RefusingNode):
        def __init__(self):
            seen.extend(pool["num_threads"] for pool in threadpool_info())
            super().__init__()

    assert run_node(CountingNode, args=[]) == 1
    assert seen and set(seen) == {1}
