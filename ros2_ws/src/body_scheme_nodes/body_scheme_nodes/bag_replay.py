"""bag_replay: publish a recorded session's topics at the original timing, faster, or as fast as scheme_node keeps up.

Each message of the selected bag topics is published on the topic's name made relative (``/observations`` ->
``observations``, so the node's namespace and remappings apply as for scheme_node's subscriptions), in log-time
order, with reliable QoS, depth 100.

Timing (``rate``)
-----------------
``rate > 0``: message ``i`` is published ``(log_i - log_0) / rate`` after the start (1.0: original timing, 2.0: twice
as fast). ``rate = 0``: as fast as the consumer keeps up: at most ``max_in_flight`` ``/observations`` messages are
ahead of what scheme_node reports on ``body_scheme/progress`` (the number of observation messages it has decided:
learnt, refused or shed; counted from the start of the replay), so the replay waits for learning. In this mode the
replay starts only once ``observations`` has a subscriber and scheme_node's count has arrived (it is latched: the
count it had before the replay is not the replay's); without
``/observations`` among the topics there is no backpressure. ``rate > 0`` waits for no one: when scheme_node learns
slower than the replay, its samples wait and, past its ``max_sample_age``, are shed (counted on /diagnostics); the
node warns when scheme_node's progress falls more than ``LAG_WARNING`` observation messages behind.

Stamps (``restamp``)
--------------------
``restamp: true`` moves every header stamp into the present so that scheme_node's pairing (which compares stamps
with its own clock, ``pairing_grace``) works as it does live: with ``rate > 0`` the stamps are shifted so that the
first message is stamped at the start time and compressed by ``rate`` (a message is stamped its original latency
``(log - header) / rate`` before it is published). With ``rate = 0`` a message is stamped with the time it is
published (strictly increasing, so in the bag's log-time order). ``restamp: false`` keeps the original stamps;
scheme_node's clock is then far past them, so it decides each observation in the first timer tick after it arrives,
which pairs correctly only if the command arrives first.

The pairing rule depends only on the stamps' order and on each observation's age after its command compared with
``settle_time`` and ``max_delay`` (body_scheme_core.pairing). ``rate > 0`` keeps the order of the header stamps and
divides the ages by ``rate``; ``rate = 0`` keeps the log-time order (the same for bags whose header stamps are their
log times, as the shipped ones) and shrinks the ages to the publishing pace (tens of microseconds). So an observation
that was stale in the original (older than ``max_delay``) can become fresh, and one that came after
``settle_time`` can come before it. With the shipped bags (0.1 s command period, observations 5 ms after their
command) and the default pairing (``settle_time`` 0, ``max_delay`` 2 s) nothing changes: the replay pairs exactly as
``replay_offline`` does and ends with the same body scheme.

Other stacks' recordings (``source_map``)
-----------------------------------------
With ``source_map`` (a YAML file, :mod:`.sources`), ``bag_path`` is another stack's bag (aruco_ros or apriltag_ros
on ``/tf``, motion capture, ...) or a table (``.csv``, ``.jsonl``): it is translated at start into the two streams
scheme_node learns from, ``joint_commands`` and ``observations`` (one sample per pose at which the arm stood still),
which are then replayed as above; ``topics`` is not used. What the import dropped is logged by reason.

The node keeps running after the end, so that ``bag_replay/done`` stays available; stop it with Ctrl-C.
"""

from __future__ import annotations

import math
import time

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from std_msgs.msg import Bool, UInt64

from body_scheme_core.errors import InvalidInputError

from .bag_io import MESSAGE_CLASSES, BagError, bag_topics, read_messages
from .in_flight import InFlight
from .qos import LATCHED
from .ros_parameters import refuse_parameter_changes
from .sources import SourceMap, translate
from .spin import run_node

__all__ = ["BagReplay", "DEFAULT_TOPICS", "main"]

DEFAULT_TOPICS = ["/joint_commands", "/observations", "/ground_truth/marker_poses"]
#: The bag topic whose messages scheme_node counts on body_scheme/progress, and the commands' topic.
BACKPRESSURE_TOPIC, COMMANDS = "/observations", "/joint_commands"
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
#: Seconds between timer ticks; each tick publishes every message that is due.
TICK = 0.005
#: Smallest spacing of restamped stamps in rate 0, ns: keeps them distinct as float seconds (ulp ~0.24 us in 2023).
MIN_SPACING_NS = 1_000
#: Rate 0: warn when body_scheme/progress has not moved for this long while messages wait, s.
STALL_WARNING = 5.0
#: Rate > 0: warn when scheme_node's progress is this many observation messages behind.
LAG_WARNING = 50


class BagReplay(Node):
    """Publishes a recorded session's topics (timing and stamps: see the module docstring).

    Parameters
    ----------
    bag_path : string  (required)              rosbag2 directory of a recorded session
    rate : double 1.0                          1.0 original timing, 2.0 twice as fast, 0.0 backpressure
    topics : string[] ["/joint_commands", "/observations", "/ground_truth/marker_poses"]
                                               bag topics to publish (types: bag_io.MESSAGE_CLASSES)
    restamp : bool true                        move header stamps into the present (module docstring)
    start_delay : double 1.0 s                 wait before the first message (for subscribers to connect)
    max_in_flight : int 3                      rate 0: observation messages published but not yet decided; a
                                               sample waits for about this many learning steps, which must stay
                                               under scheme_node's max_sample_age (5 s) or it is shed
    source_map : string ""                     YAML mapping another stack's topics or a table to samples
                                               (module docstring); "" replays our own session bags

    Publishers
    ----------
    <topic without leading slash> : the bag's type, reliable, depth 100
    bag_replay/done : std_msgs/Bool  (transient local)   true when every message is out; false if the bag broke midway

    Subscriptions
    -------------
    body_scheme/progress : std_msgs/UInt64   scheme_node's count of observation messages decided (rate 0; transient
                                             local)
    """

    def __init__(self, **node_options):
        super().__init__("bag_replay", **node_options)
        self.bag_path = self.declare_parameter("bag_path", "").value
        self.rate = float(self.declare_parameter("rate", 1.0).value)
        self.topics = list(self.declare_parameter("topics", DEFAULT_TOPICS).value)
        self.restamp = bool(self.declare_parameter("restamp", True).value)
        self.start_delay = float(self.declare_parameter("start_delay", 1.0).value)
        self.max_in_flight = int(self.declare_parameter("max_in_flight", 3).value)
        self.source_map = self.declare_parameter("source_map", "").value
        _check_parameters(self.bag_path, self.rate, self.topics, self.start_delay, self.max_in_flight)

        if self.source_map:
            translation = translate(self.bag_path, SourceMap.from_yaml(self.source_map))
            self.get_logger().info(f"imported {self.bag_path} with {self.source_map}: {translation.summary()}")
            self._messages = (item for item in translation.messages)
            self.total = len(translation.messages)
            available = {COMMANDS: ("sensor_msgs/msg/JointState", 0),
                         BACKPRESSURE_TOPIC: ("body_scheme_msgs/msg/MarkerPoses", 0)}
            self.topics = list(available)
        else:
            available = bag_topics(self.bag_path)
            missing = [topic for topic in self.topics if topic not in available]
            if missing:
                self.get_logger().warn(f"bag {self.bag_path} has no topic(s) {missing}; replaying the others")
            self._messages = read_messages(self.bag_path, self.topics)  # checks the types at once
            self.total = sum(available[topic][1] for topic in self.topics if topic in available)
        self.publishers_by_topic = {
            topic: self.create_publisher(MESSAGE_CLASSES[available[topic][0]], topic.lstrip("/"), RELIABLE)
            for topic in self.topics if topic in available}
        self.pub_done = self.create_publisher(Bool, "bag_replay/done", LATCHED)
        self._progress_subscription = self.create_subscription(UInt64, "body_scheme/progress", self._on_progress,
                                                               LATCHED)
        refuse_parameter_changes(self)

        self.published = dict.fromkeys(self.publishers_by_topic, 0)
        self.in_flight = InFlight()         # observation messages published and not yet decided by scheme_node
        self._next = None                   # next BagMessage, read ahead
        self._start_at = self._now() + int(self.start_delay * 1e9)
        self._anchor = None                 # (wall ns, log ns) of the first message
        self._last_stamp = None             # rate 0: latest restamped header stamp, ns
        self._waits = 0                     # ticks that ended because of backpressure
        self._finished = False
        self._started_wall = None
        self.timer = self.create_timer(TICK, self._on_timer)
        self.get_logger().info(
            f"bag_replay: {self.total} messages of {sorted(self.publishers_by_topic)} from {self.bag_path}, "
            f"rate {self.rate:g}{' (backpressure)' if self.rate == 0 else ''}, restamp {self.restamp}")

    # -- callbacks ----------------------------------------------------------------------------------------------
    def _on_progress(self, msg):
        self.in_flight.on_progress(msg.data, time.monotonic())

    def _on_timer(self):
        if self._finished:
            return
        now = self._now()
        if self._anchor is None and not self._ready(now):
            return
        try:
            self._publish_due(now)
        except BagError as error:
            self.get_logger().error(f"stopping the replay: {error}")
            self._finish(success=False)

    # -- the work -----------------------------------------------------------------------------------------------
    def _ready(self, now):
        """Whether the replay may start: after start_delay and, in rate 0, once scheme_node is connected."""
        if now < self._start_at:
            return False
        if self.rate == 0 and BACKPRESSURE_TOPIC in self.publishers_by_topic:
            connected = (self.publishers_by_topic[BACKPRESSURE_TOPIC].get_subscription_count() > 0
                         and self.in_flight.progress is not None)  # scheme_node's count, at once (latched)
            if not connected:
                self.get_logger().info("rate 0: waiting for a subscriber of observations and a publisher of "
                                       "body_scheme/progress (scheme_node)", throttle_duration_sec=5.0)
                return False
        return True

    def _publish_due(self, now):
        if self._next is None:
            self._next = next(self._messages, None)
        if self._anchor is None:
            if self._next is None:
                self._finish(success=True)
                return
            self._anchor = (now, self._next.log_time)
            self.in_flight.start(time.monotonic())
            self._started_wall = time.monotonic()
        while self._next is not None:
            if self.rate > 0:
                publish_ns = self._anchor[0] + round((self._next.log_time - self._anchor[1]) / self.rate)
                if publish_ns > now:
                    self._warn_if_falling_behind()
                    return
            else:
                if self.in_flight.count() >= self.max_in_flight:
                    self._waits += 1
                    if self.in_flight.stalled_for(time.monotonic()) > STALL_WARNING:
                        self.get_logger().warn(
                            f"rate 0: {self.in_flight.count()} observation messages in flight and no progress for "
                            f"{STALL_WARNING:g} s: is scheme_node running?", throttle_duration_sec=STALL_WARNING)
                    return
                publish_ns = self._now()
            self._publish(self._next, publish_ns)
            self._next = next(self._messages, None)
        self._finish(success=True)

    def _warn_if_falling_behind(self):
        """rate > 0 does not wait: warn when scheme_node lags so far behind that its samples wait or are shed."""
        behind = self.in_flight.count()
        if self._progress_subscription.get_publisher_count() > 0 and behind > LAG_WARNING:
            self.get_logger().warn(
                f"scheme_node is {behind} observation messages behind at rate {self.rate:g}: its samples "
                f"wait, and past its max_sample_age they are shed; lower the rate or use rate 0",
                throttle_duration_sec=5.0)

    def _publish(self, item, publish_ns):
        msg = item.msg
        if self.restamp and hasattr(msg, "header"):
            # Integer nanoseconds throughout: float64 cannot hold today's stamps to the nanosecond.
            if self.rate > 0:
                latency = item.log_time - Time.from_msg(msg.header.stamp).nanoseconds
                stamp = publish_ns - round(latency / self.rate)
            else:
                stamp = publish_ns if self._last_stamp is None else max(publish_ns, self._last_stamp + MIN_SPACING_NS)
                self._last_stamp = stamp
            msg.header.stamp = Time(nanoseconds=stamp).to_msg()
        self.publishers_by_topic[item.topic].publish(msg)
        self.published[item.topic] += 1
        self.in_flight.sent += item.topic == BACKPRESSURE_TOPIC

    def _finish(self, success):
        self._finished = True
        self.timer.cancel()
        self.pub_done.publish(Bool(data=success))
        seconds = time.monotonic() - self._started_wall if self._started_wall is not None else 0.0
        count = sum(self.published.values())
        rate = f", {count / seconds:.0f} messages/s" if seconds > 0 else ""
        by_topic = ", ".join(f"{topic} {n}" for topic, n in self.published.items())
        taken_in = self.in_flight.decided
        backpressure = f"; waited for scheme_node in {self._waits} ticks" if self.rate == 0 else ""
        if taken_in:
            backpressure += f"; scheme_node has taken in {taken_in} observation messages so far"
        log = self.get_logger().info if success else self.get_logger().error
        log(f"replay {'finished' if success else 'FAILED'}: {count} of {self.total} messages in {seconds:.2f} s"
            f"{rate} ({by_topic}){backpressure}")

    def _now(self):
        return self.get_clock().now().nanoseconds

    def destroy_node(self):
        self._messages.close()  # closes the bag file
        return super().destroy_node()


def _check_parameters(bag_path, rate, topics, start_delay, max_in_flight):
    if not bag_path:
        raise InvalidInputError("parameter bag_path is required: the rosbag2 directory to replay")
    if not (math.isfinite(rate) and rate >= 0):
        raise InvalidInputError(f"rate must be >= 0 (0: as fast as scheme_node keeps up), got {rate}")
    if not topics or any(not topic.startswith("/") for topic in topics):
        raise InvalidInputError(f"topics must be a non-empty list of bag topic names (absolute), got {topics}")
    if not (math.isfinite(start_delay) and start_delay >= 0):
        raise InvalidInputError(f"start_delay must be >= 0 s, got {start_delay}")
    if max_in_flight < 1:
        raise InvalidInputError(f"max_in_flight must be >= 1, got {max_in_flight}")


def main(args=None):
    return run_node(BagReplay, args, threads=1)


if __name__ == "__main__":
    raise SystemExit(main())
