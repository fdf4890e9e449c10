"""System tests of the whole graph as processes over DDS: sim_node -> [tracker_node ->] scheme_node -> control_node."""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from body_scheme_apps.live_demo import domain_id, format_summary, run_live_demo

pytestmark = pytest.mark.system


def assert_story(result, block, repair, ik_tolerance):
    """The true structure; the block at ``block`` detected and adapted to, the repair at ``repair`` recognised (also on
    /diagnostics); every IK target reached by the simulated end effector within ``ik_tolerance`` m."""
    summary = format_summary(result)
    assert result.structure_learned(), summary

    def first(kind, lo, hi):
        return next((e for e in result.events if e["kind"] == kind and lo <= e["step"] < hi), None)

    assert first("mismatch_detected", block, block + 20) is not None, summary
    assert first("model_replaced", block, block + 30) or first("model_reinstated", block, block + 30), summary
    assert first("model_reinstated", repair, repair + 15) is not None, summary
    # The detection is visible on /diagnostics (cumulative event counters of the scheme status).
    assert result.scheme_status.get("events.mismatch_detected", 0) >= 1, result.scheme_status
    assert result.scheme_status.get("events.model_reinstated", 0) >= 1, result.scheme_status
    reached = [r["reached_error"] for r in result.ik]
    assert len(reached) == 3 and all(r is not None and r < ik_tolerance for r in reached), (result.ik, summary)


def test_the_monitor_joins_the_domain_of_the_nodes(monkeypatch):
    """`make demo` in a shell with ROS_DOMAIN_ID set: the node processes inherit it, so the monitor must use it too
    (it used domain 0 and never saw the graph); an explicit environment wins."""
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert domain_id() == 42
    assert domain_id({"ROS_DOMAIN_ID": "7"}) == 7
    monkeypatch.setenv("ROS_DOMAIN_ID", "")
    assert domain_id() == 0 and domain_id({}) == 0


def assert_recording_decodes(bag, recorded):
    """The demo's mcap decodes channel by channel with the mcap library's ROS 2 support, from its embedded schemas
    alone (as Foxglove reads it), and holds every recorded topic with the counts the recorder wrote."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from body_scheme_apps.live_demo import RECORDED_TOPICS

    (path,) = bag.glob("*.mcap")
    counts, kinds = {}, {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _, decoded in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            kinds.setdefault(channel.topic, type(decoded).__name__)
    expected = {("/" + t).replace("//", "/") for t, _, _ in RECORDED_TOPICS}
    assert {t for t, n in recorded.items() if n} <= set(counts) <= expected, (counts, recorded)
    assert counts == {t: n for t, n in recorded.items() if n}
    for topic in ("/joint_commands", "/observations", "/predicted_poses", "/body_scheme/structure",
                  "/body_scheme/events", "/diagnostics", "/body_scheme/markers", "/tf",
                  "/body_scheme/robot_description"):
        assert counts.get(topic, 0) > 0, (topic, counts)
    assert "ros_distro: jazzy" in (bag / "metadata.yaml").read_text()


def test_live_graph_with_rendered_images_learns_detects_recovers_and_moves_the_arm(ros_env, tmp_path):
    """The product's pipeline: camera images -> tracker_node -> scheme_node -> control_node, from scratch, recorded
    to an mcap that decodes.

    The true structure is learned from ArUco poses alone, the blocked end-effector joint is detected and its model
    replaced, the repair reinstates the remembered model (all on /diagnostics too), and IK on the learned scheme
    (within its training range) puts the simulated end effector (ground truth) within 60 mm of each target.
    """
    result = run_live_demo(tmp_path, steps=300, period=0.05, faults=("120:block_joint:5:0.8", "220:repair"),
                           perception="rendered", n_targets=3, env=ros_env, log=lambda text: None)
    assert result.n_observations >= 0.9 * result.steps, format_summary(result)  # tracker_node's reached scheme_node
    assert_story(result, block=120, repair=220, ik_tolerance=0.06)
    # After the repair the scheme predicts the tool again (measured 1.5 mm against the true pose; the noise-model
    # twin of this test, 45 mm at 10 mm / 3 deg, went in CI time's cuts).
    assert np.mean([e for s, e in result.prediction_error if s >= 260]) < 0.03, format_summary(result)
    assert_recording_decodes(tmp_path / "session", result.recorded)


def _processes_using(path):
    """PIDs of the processes whose command line names ``path`` (a node started with a parameter file in it)."""
    pids = []
    for proc in pathlib.Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and str(path).encode() in (proc / "cmdline").read_bytes():
                pids.append(int(proc.name))
        except OSError:  # gone meanwhile
            pass
    return pids


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_demo_stops_its_nodes_and_says_so(sig, ros_env, tmp_path):
    """Ctrl-C (SIGINT) or a ``kill`` (SIGTERM) while the demo babbles: it stops every node it started (none babbles on
    in the domain), prints one line and exits 128 + the signal. (rclpy's own handlers let a Ctrl-C run the demo to
    its end, and a SIGTERM leave the nodes running.)"""
    out = tmp_path / "demo"
    env = {k: v for k, v in ros_env.items() if k != "PYTHONUNBUFFERED"}  # the demo's lines come as they are printed
    demo = subprocess.Popen([sys.executable, "-m", "body_scheme_apps.live_demo", "--perception", "noise", "--out",
                             str(out)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        printed = []
        for line in demo.stdout:  # until the graph is up and babbling (or the demo ended: then the asserts say why)
            printed.append(line)
            if line.startswith("babbling"):
                break
        deadline = time.monotonic() + 60  # the demo printed its line right after starting sim_node
        while len(set(_processes_using(out)) - {demo.pid}) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)
        nodes = {pid: pathlib.Path(f"/proc/{pid}/cmdline").read_bytes()[:200] for pid in _processes_using(out)
                 if pid != demo.pid}
        assert len(nodes) == 3, (printed, nodes)  # scheme_node, control_node and sim_node
        demo.send_signal(sig)
        stdout, stderr = demo.communicate(timeout=120)
        assert demo.returncode == 128 + sig, (printed, stdout, stderr)
        assert f"live_demo: interrupted ({sig.name})" in stderr.splitlines() and "Traceback" not in stderr, stderr
        assert _processes_using(out) == [], (printed, stdout, stderr)
        assert not (out / "summary.json").exists()
    finally:  # never leave a demo or a node of it behind, pass or fail
        demo.kill()
        for pid in _processes_using(out):
            os.kill(pid, signal.SIGKILL)
