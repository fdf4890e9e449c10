"""GraphRecorder writes each topic's QoS into the bag, as ``ros2 bag record`` does (issue 20)."""

import time

import rclpy
import yaml
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String

from body_scheme_nodes.qos import LATCHED, RECENT_EVENTS
from body_scheme_nodes.recorder import GraphRecorder


def test_latched_topics_are_recorded_with_their_qos_so_a_replay_latches_them(tmp_path, context):
    node = rclpy.create_node("recorder_test", context=context)
    try:
        node.create_publisher(String, "description", LATCHED).publish(String(data="latched before recording"))
        recorder = GraphRecorder(node, tmp_path / "bag", [("description", String, True), ("chatter", String, False),
                                                               ("events", String, RECENT_EVENTS)])
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 60
        while recorder.counts["/description"] == 0 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        executor.shutdown()
        recorder.close()
    finally:
        node.destroy_node()
    info = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
           for t in info["topics_with_message_count"]}
    (latched,), (volatile,), (events,) = qos["/description"], qos["/chatter"], qos["/events"]
    assert (latched["durability"], latched["reliability"], latched["depth"]) == ("transient_local", "reliable", 1)
    assert (volatile["durability"], volatile["reliability"], volatile["depth"]) == ("volatile", "reliable", 100)
    assert (events["durability"], events["reliability"], events["depth"]) == ("transient_local", "reliable", 100)
