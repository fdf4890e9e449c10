"""BatchIntake with the real rclpy: the executor never dispatches it; take() returns every waiting message at once."""

import time

import pytest
import rclpy
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

from body_scheme_nodes.intake import BatchIntake


@pytest.fixture
def node(context):
    """A node in an rclpy context on a domain of this test alone (conftest)."""
    node = rclpy.create_node("intake_test", context=context)
    try:
        yield node
    finally:
        node.destroy_node()


def _publish(node, intake, n):
    publisher = node.create_publisher(JointState, "commands", 100)
    deadline = time.monotonic() + 60
    while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    for k in range(n):
        publisher.publish(JointState(name=["j"], position=[float(k)]))
    _delivered(publisher)
    return publisher


def _delivered(publisher):
    """Wait until the (reliable) intake acknowledged every message published: a condition, not a time window."""
    assert publisher.wait_for_all_acked(Duration(seconds=60))


def test_take_returns_every_waiting_message_oldest_first_with_its_reception_time(node):
    intake = BatchIntake(node, JointState, "commands", 100)
    before = time.time()
    _publish(node, intake, 30)
    messages, deadline = [], time.monotonic() + 60
    while len(messages) < 30 and time.monotonic() < deadline:
        messages += intake.take()
        time.sleep(0.01)
    after = time.time()
    assert [msg.position[0] for msg, _ in messages] == [float(k) for k in range(30)]
    received = [t for _, t in messages]
    assert received == sorted(received) and before <= received[0] and received[-1] <= after
    assert intake.take() == []


def test_the_executor_never_dispatches_a_batch_intake(node):
    """Spinning with messages waiting calls no callback (its callback would raise) and leaves them for take()."""
    intake = BatchIntake(node, JointState, "commands", 100)
    _publish(node, intake, 5)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    for _ in range(20):
        executor.spin_once(timeout_sec=0.01)
    executor.shutdown()
    assert len(intake.take()) == 5


def test_messages_beyond_the_depth_are_lost_oldest_first(node):
    """The depth is the bound documented for queue_depth: a longer backlog keeps the newest messages."""
    intake = BatchIntake(node, JointState, "commands", 10)
    _publish(node, intake, 25)
    assert [msg.position[0] for msg, _ in intake.take()] == [float(k) for k in range(15, 25)]


def test_losses_inside_dds_are_counted_from_the_publishers_sequence_numbers(node):
    """Fast DDS reports nothing when keep-last overwrites a message (its message-lost event stays silent); the gap in
    the publisher's sequence numbers counts them: whatever was sent is taken or counted as lost."""
    intake = BatchIntake(node, JointState, "commands", 10)
    _publish(node, intake, 25)
    assert len(intake.take()) == 10 and intake.lost == 0  # the first take sets the baseline: before it, unknown
    publisher = node.create_publisher(JointState, "commands", 100)  # a second publisher: numbers interleave
    time.sleep(0.3)
    node.destroy_publisher(publisher)
    time.sleep(0.3)
    _publish_more(node, 40)
    assert len(intake.take()) == 10 and intake.lost == 30 and intake.full_queue_takes == 0


def _publish_more(node, n):
    publisher = next(p for p in node.publishers if p.topic_name == "/commands")
    for k in range(n):
        publisher.publish(JointState(name=["j"], position=[float(k)]))
    _delivered(publisher)


def test_a_message_larger_than_max_bytes_is_refused_before_it_is_deserialized(node):
    intake = BatchIntake(node, JointState, "commands", 10, max_bytes=1000)
    publisher = _publish(node, intake, 1)
    publisher.publish(JointState(name=[f"joint_{k}" for k in range(100)], position=[0.0] * 100))
    _delivered(publisher)
    assert len(intake.take()) == 1 and intake.take_refused() == [pytest.approx(2_000, rel=0.5)]
    assert intake.take_refused() == []


def test_requests_are_taken_in_batches_and_each_caller_gets_its_answer(node):
    """RequestIntake: 50 concurrent calls (a service of rclpy's default depth 10 lost 39 of them before issue 20) are
    all taken, in order, and each answer reaches its own caller."""
    from rclpy.qos import QoSProfile
    from std_srvs.srv import SetBool

    from body_scheme_nodes.intake import RequestIntake

    intake = RequestIntake(node, SetBool, "toggle", 100)
    # 50 callers. Every caller's reader sees every response (they share a topic) and keeps its depth of them: callers
    # that wait together need a depth of at least their number, or they lose their own answer among the others'.
    clients = [node.create_client(SetBool, "toggle", qos_profile=QoSProfile(depth=100)) for _ in range(50)]
    assert all(client.wait_for_service(timeout_sec=60) for client in clients)
    futures = [client.call_async(SetBool.Request(data=k % 2 == 0)) for k, client in enumerate(clients)]
    requests, deadline = [], time.monotonic() + 60
    while len(requests) < 50 and time.monotonic() < deadline:
        requests += intake.take()
        time.sleep(0.01)
    assert [r.data for r, _ in requests] == [k % 2 == 0 for k in range(50)]
    for k, (request, header) in enumerate(requests):
        intake.answer(header, SetBool.Response(success=request.data, message=str(k)))
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + 60
    while not all(f.done() for f in futures) and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    executor.shutdown()
    assert [f.result().message for f in futures] == [str(k) for k in range(50)]


def test_slow_requests_are_served_in_a_thread_of_their_own_and_the_excess_is_answered_busy(node):
    """ServiceWorker: take() hands requests to the service thread and returns at once, however slow the handler (50
    slow ~/load requests held the executor's thread 25 s before); at most max_waiting wait, the rest are answered
    busy at once; every caller gets an answer, and a handler's exception is a failed answer."""
    import threading

    from rclpy.qos import QoSProfile
    from std_srvs.srv import SetBool

    from body_scheme_nodes.intake import RequestIntake, ServiceWorker

    release, served_in = threading.Event(), set()

    def slow(request, response):
        release.wait(30)
        served_in.add(threading.current_thread().name)
        if not request.data:
            raise RuntimeError("bad request")
        response.success, response.message = True, "served"
        return response

    worker = ServiceWorker({"slow": (RequestIntake(node, SetBool, "slow", 100), slow)}, 3,
                           lambda name, limit: f"busy ({limit})", lambda text: None)
    try:
        clients = [node.create_client(SetBool, "slow", qos_profile=QoSProfile(depth=100)) for _ in range(10)]
        assert all(client.wait_for_service(timeout_sec=60) for client in clients)
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        futures, deadline = [], time.monotonic() + 30
        for k, client in enumerate(clients):  # one by one: the first three wait, the first of them fails
            futures.append(client.call_async(SetBool.Request(data=k != 0)))
            while sum(worker.counters().values()) <= k and time.monotonic() < deadline:
                worker.take()  # returns although the handler blocks
                executor.spin_once(timeout_sec=0.01)
        assert worker.counters() == {"slow.busy": 7, "slow.waiting": 3}
        release.set()
        while not all(f.done() for f in futures) and time.monotonic() < deadline:
            worker.take()
            executor.spin_once(timeout_sec=0.01)
        executor.shutdown()
        messages = sorted(f.result().message for f in futures)
        assert messages == ["busy (3)"] * 7 + ["served"] * 2 + ["slow failed: RuntimeError: bad request"]
        assert worker.counters() == {"slow.busy": 7, "slow.answered": 2, "slow.failed": 1}  # none waits
        assert served_in == {"services"}
    finally:
        release.set()
        worker.stop()
