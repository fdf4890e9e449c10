"""System test of tracker_node: sim_node renders camera images, tracker_node turns them into marker poses over DDS."""

from __future__ import annotations

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray

from body_scheme_core.perception import DOCUMENTED_TRANS_ERROR_MEDIAN
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes import conversions
from body_scheme_sim.robots import robot_files

pytestmark = pytest.mark.system


def stamp_key(header):
    return header.stamp.sec, header.stamp.nanosec


class Listener:
    """Keeps tracked observations, their PoseArrays and the simulator's ground truth by header stamp."""

    def __init__(self, node):
        self.observed, self.arrays, self.truth, self.diagnostics = {}, {}, {}, {}
        node.create_subscription(MarkerPoses, "observations", self._keep(self.observed), 100)
        node.create_subscription(PoseArray, "observations/poses", self._keep(self.arrays), 100)
        node.create_subscription(MarkerPoses, "ground_truth/marker_poses", self._keep(self.truth), 100)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    @staticmethod
    def _keep(store):
        return lambda msg: store.__setitem__(stamp_key(msg.header), msg)

    def _on_diagnostics(self, msg):
        for status in msg.status:
            self.diagnostics[status.name] = status

    def matched(self):
        """Stamps seen on both the tracker's observations (with at least one marker) and the ground truth."""
        return sorted(k for k in self.observed if k in self.truth and self.observed[k].marker_ids)


def test_tracker_node_turns_rendered_images_into_marker_poses(start_node, ros_node, spin_until):
    """Marker poses tracked in sim_node's rendered images arrive with the image stamp, close to the ground truth."""
    _, markers_path = robot_files("powercube_6dof")
    sim = start_node("body_scheme_nodes", "sim_node", {
        "robot": "powercube_6dof", "perception_mode": "rendered", "babbling": True, "babbling_period": 0.1,
        "markers_of_interest": [6, 7], "seed": 1})
    tracker = start_node("body_scheme_nodes", "tracker_node", {"markers_path": str(markers_path),
                                                               "marker_size": 0.0})
    listener = Listener(ros_node)

    assert spin_until(lambda: len(listener.matched()) >= 15, timeout=60), (
        f"{len(listener.observed)} observations, {len(listener.truth)} ground truths\n"
        f"--- sim_node ---\n{sim.output()}\n--- tracker_node ---\n{tracker.output()}")

    errors = []
    for key in listener.matched():
        observed_stamp, observed, rejected = conversions.observations_from_msg(listener.observed[key])
        _, truth, _ = conversions.observations_from_msg(listener.truth[key])
        assert rejected == [] and listener.observed[key].header.frame_id == "camera"
        assert set(observed) <= set(truth)
        errors += [np.linalg.norm(observed[i][:3, 3] - truth[i][:3, 3]) for i in observed]
    assert len(errors) >= 15 * 3
    assert np.median(errors) <= DOCUMENTED_TRANS_ERROR_MEDIAN
    # Each pose carries its covariance from the corners' noise: positive definite, largest along the ray.
    for item in listener.observed[listener.matched()[-1]].poses:
        covariance = np.array(item.covariance).reshape(6, 6)
        ray = np.array([item.pose.position.x, item.pose.position.y, item.pose.position.z])
        ray /= np.linalg.norm(ray)
        assert np.all(np.linalg.eigvalsh(covariance) > 0.0)
        assert ray @ covariance[:3, :3] @ ray > 0.9 * np.linalg.eigvalsh(covariance[:3, :3])[-1]

    # The PoseArray twin carries the same stamp and the same positions.
    key = next(k for k in listener.matched() if k in listener.arrays)
    positions = [(p.pose.position.x, p.pose.position.y) for p in listener.observed[key].poses]
    assert [(p.position.x, p.position.y) for p in listener.arrays[key].poses] == positions

    def tracker_ok():
        status = listener.diagnostics.get("/tracker_node: tracker")
        return status is not None and status.level == DiagnosticStatus.OK
    assert spin_until(tracker_ok, timeout=60), listener.diagnostics
