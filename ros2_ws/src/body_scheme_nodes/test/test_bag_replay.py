"""bag_replay in-process: restamping, backpressure, and refusing bad parameters and broken bags."""


import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, UInt64

from body_scheme_core.errors import InvalidInputError
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes.bag_io import BagError, write_session
from body_scheme_nodes.bag_replay import BagReplay, main
from body_scheme_nodes.graph import spin_until
from body_scheme_nodes.qos import LATCHED
from body_scheme_sim.sessions import record_session

N_STEPS = 20


@pytest.fixture(scope="module")
def session_and_bag(tmp_path_factory):
    """A 20-step planar session (commands every 0.1 s, observations 5 ms later) and its bag."""
    session = record_session("planar_2dof", N_STEPS, seed=2)
    return session, write_session(session, tmp_path_factory.mktemp("bags") / "planar")


class Listener:
    """Records the stamps of replayed commands and observations; optionally acts as scheme_node's progress."""

    def __init__(self, context):
        self.node = rclpy.create_node("listener", context=context)
        self.commands, self.observations, self.done = [], [], None
        self.node.create_subscription(JointState, "joint_commands", lambda m: self.commands.append(_ns(m)), 100)
        self.node.create_subscription(MarkerPoses, "observations", lambda m: self.observations.append(_ns(m)), 100)
        self.node.create_subscription(Bool, "bag_replay/done", self._done, LATCHED)
        self.progress = self.node.create_publisher(UInt64, "body_scheme/progress", LATCHED)  # as scheme_node

    def _done(self, msg):
        self.done = msg.data


def _ns(msg):
    return Time.from_msg(msg.header.stamp).nanoseconds


def _replay(context, bag, **parameters):
    overrides = [Parameter("bag_path", value=str(bag)), Parameter("start_delay", value=0.0)]
    overrides += [Parameter(name, value=value) for name, value in parameters.items()]
    return BagReplay(context=context, parameter_overrides=overrides)


def _run(context, nodes):
    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    return executor


def test_rate_compresses_the_original_stamps_and_keeps_their_order(context, session_and_bag):
    """rate 20 with restamp: stamps start now and keep the original spacing divided by 20."""
    session, bag = session_and_bag
    listener = Listener(context)
    replay = _replay(context, bag, rate=20.0)
    executor = _run(context, [listener.node, replay])
    assert spin_until(executor, lambda: listener.done is not None and len(listener.observations) == N_STEPS, 10)
    assert listener.done is True and len(listener.commands) == N_STEPS
    first = int(session.command_stamps[0])
    expected_commands = [(int(s) - first) / 20 for s in session.command_stamps]
    expected_observations = [(int(s) - first) / 20 for s in session.observation_stamps]
    start = listener.commands[0]
    assert [c - start for c in listener.commands] == pytest.approx(expected_commands, abs=2)
    assert [o - start for o in listener.observations] == pytest.approx(expected_observations, abs=2)
    assert abs(start - replay.get_clock().now().nanoseconds) < 30e9, "stamped in the present, not in 2023"
    replay.destroy_node()
    listener.node.destroy_node()


def test_restamp_false_keeps_the_original_stamps(context, session_and_bag):
    """With restamp false every header stamp is the recorded one."""
    session, bag = session_and_bag
    listener = Listener(context)
    replay = _replay(context, bag, rate=50.0, restamp=False)
    executor = _run(context, [listener.node, replay])
    assert spin_until(executor, lambda: listener.done is not None and len(listener.observations) == N_STEPS, 10)
    assert listener.commands == [int(s) for s in session.command_stamps]
    assert listener.observations == [int(s) for s in session.observation_stamps]
    replay.destroy_node()
    listener.node.destroy_node()


def test_rate_zero_keeps_at_most_max_in_flight_observations_ahead(context, session_and_bag):
    """rate 0 waits for the consumer's count, publishes only max_in_flight observations beyond it (counted from the
    start: a count of 7 from before the replay is not the replay's), then all when it keeps up."""
    _, bag = session_and_bag
    listener = Listener(context)
    replay = _replay(context, bag, rate=0.0, max_in_flight=3)
    executor = _run(context, [listener.node, replay])
    spin_until(executor, lambda: False, 0.5)  # no count yet: no replay
    assert len(listener.observations) == 0 and listener.done is None
    listener.progress.publish(UInt64(data=7))
    assert spin_until(executor, lambda: len(listener.observations) == 3, 10)
    spin_until(executor, lambda: False, 0.3)  # no progress: the gate stays closed
    assert len(listener.observations) == 3 and len(listener.commands) == 3
    listener.progress.publish(UInt64(data=9))
    assert spin_until(executor, lambda: len(listener.observations) == 5, 10)
    spin_until(executor, lambda: False, 0.2)
    assert len(listener.observations) == 5

    def keep_up():
        listener.progress.publish(UInt64(data=7 + len(listener.observations)))

    assert spin_until(executor, lambda: listener.done is not None and len(listener.observations) == N_STEPS, 20,
                 during=keep_up)
    assert listener.done is True and len(listener.observations) == N_STEPS == len(listener.commands)
    # Each observation is stamped after its command and before the next one, as recorded.
    merged = [stamp for pair in zip(listener.commands, listener.observations, strict=True) for stamp in pair]
    assert merged == sorted(merged) and len(set(merged)) == len(merged)
    replay.destroy_node()
    listener.node.destroy_node()


def test_a_bag_broken_midway_ends_with_done_false(context, session_and_bag, tmp_path):
    """A bag that turns out corrupt while replaying stops the replay and latches done = false."""
    _, bag = session_and_bag
    broken = tmp_path / "broken"
    broken.mkdir()
    for part in bag.iterdir():
        data = bytearray(part.read_bytes())
        if part.suffix == ".mcap":
            data[len(data) // 2:len(data) // 2 + 64] = bytes(range(64))  # inside the compressed chunks
        (broken / part.name).write_bytes(bytes(data))
    listener = Listener(context)
    replay = _replay(context, broken, rate=50.0)
    executor = _run(context, [listener.node, replay])
    assert spin_until(executor, lambda: listener.done is not None, 10)
    assert listener.done is False
    replay.destroy_node()
    listener.node.destroy_node()


@pytest.mark.parametrize("parameters, error, message", [
    ({"bag_path": ""}, InvalidInputError, "bag_path is required"),
    ({"rate": -1.0}, InvalidInputError, "rate must be >= 0"),
    ({"max_in_flight": 0}, InvalidInputError, "max_in_flight"),
    ({"topics": ["observations"]}, InvalidInputError, "absolute"),
    ({"bag_path": "/nonexistent/bag"}, BagError, "does not exist"),
])
def test_bad_parameters_and_missing_bags_are_refused(context, session_and_bag, parameters, error, message):
    """Invalid parameters or a missing bag stop the node at construction with the reason."""
    _, bag = session_and_bag
    with pytest.raises(error, match=message):
        _replay(context, parameters.pop("bag_path", bag), **parameters)


def test_main_exits_with_code_1_on_a_missing_bag(monkeypatch):
    """The executable logs the reason and exits with 1 when the bag does not exist."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    assert main(["bag_replay", "--ros-args", "-p", "bag_path:=/nonexistent/bag"]) == 1
