"""``load_bench``: scheme_node under overload: valid command/observation pairs at 1 kHz, over DDS, for a minute.

    python -m body_scheme_apps.load_bench [--rate 1000] [--seconds 60] [--max-sample-age 0.05]
                                          [--out out/bench/load.json]

The installed scheme_node runs as its own process (the 2-DOF arm's parameters, checkpoints every second into a
temporary directory, ``max_sample_age`` as given: the live setting, see config/scheme_node.yaml) in this process's ROS
domain (``ROS_DOMAIN_ID``, as for ``make demo``). This process publishes a synthetic babbling session at ``--rate``
pairs per second and measures:

``diagnostics_max_gap_s``
    Longest time between two /diagnostics messages of the node (target <= 2).
``checkpoint_max_gap_s``
    Longest time between two writes of the checkpoint file (target <= 2 x the 1 s period).
``prediction_latency_p99_ms``
    99th percentile of (arrival of a ``predicted_poses`` message - its stamp, the sample's time) (target <= 200).
    Arrival is DDS's reception time in this process, which is itself busy publishing.
``rss_growth_mb``
    Growth of the node's resident memory from 5 s into the run to its end (target <= 50).
``uncounted_drops``
    Messages published minus those the node counted as received (``received.*`` on /diagnostics) or as lost inside
    DDS before it took them (``lost.*_messages``: keep-last overwrites, from the publisher's sequence numbers): messages
    lost with no count anywhere (target 0). Everything received is learnt, refused (``rejected.*``), shed under
    overload (``shed.*``) or still pending, each counted. ``lost_in_dds`` reports the lost ones apart.

Also reported: the samples learnt, shed and pending at the end, and the counts by reason.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import tempfile
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState

from body_scheme_apps.bench_output import report
from body_scheme_apps.live_demo import domain_id
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_msgs.msg import MarkerPoses
from body_scheme_nodes import conversions
from body_scheme_nodes.graph import NodeProcess, monitor_node

from .entry import command

__all__ = ["TARGETS", "run_load", "main"]

#: Figure -> (comparison, target).
TARGETS = {"diagnostics_max_gap_s": ("<=", 2.0), "checkpoint_max_gap_s": ("<=", 2.0),
           "prediction_latency_p99_ms": ("<=", 200.0), "rss_growth_mb": ("<=", 50.0), "uncounted_drops": ("<=", 0)}
_NODE = "/scheme_node: body scheme"


def _rss_mb(pid):
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def run_load(rate=1000.0, seconds=60.0, max_sample_age=0.05, seed=0):
    """Run the load and return the figures (a dict)."""
    tree = planar_2dof()
    n = int(rate * seconds)
    session = make_session(tree, n, seed=seed, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    with tempfile.TemporaryDirectory() as tmp, monitor_node("load_bench", domain_id()) as (node, executor):
        checkpoint = pathlib.Path(tmp) / "state.json"
        parameters = {"part_ids": [int(i) for i in tree.marker_ids], "joint_names": list(tree.action_joint_names),
                      "action_lower": [float(v) for v in tree.action_lower],
                      "action_upper": [float(v) for v in tree.action_upper],
                      "checkpoint_path": str(checkpoint), "checkpoint_period": 1.0,
                      "max_sample_age": float(max_sample_age)}
        process = None
        diagnostics, latencies, last = [], [], {}

        def on_diagnostics(msg):
            for status in msg.status:
                if status.name == _NODE:
                    diagnostics.append(time.monotonic())
                    last.clear()
                    last.update({kv.key: kv.value for kv in status.values})

        def on_predicted(msg, info):
            # DDS's reception time, not this callback's: this process is busy publishing and may run callbacks late.
            arrived = info["received_timestamp"] * 1e-9
            latencies.append(arrived - conversions.seconds_from_stamp(msg.header.stamp))

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        node.create_subscription(MarkerPoses, "predicted_poses", on_predicted, 100)
        commands = node.create_publisher(JointState, "joint_commands", 100)
        observations = node.create_publisher(MarkerPoses, "observations", 100)
        names = list(tree.action_joint_names)
        try:  # the node started is stopped, whatever comes (an interrupt too)
            process = NodeProcess("body_scheme_nodes", "scheme_node", parameters, tmp)
            deadline = time.monotonic() + 60
            while not diagnostics and time.monotonic() < deadline:  # the node is up and discovered
                executor.spin_once(timeout_sec=0.05)
            if not diagnostics:
                raise RuntimeError(f"scheme_node did not come up within 60 s:\n{process.output()}")
            checkpoint_writes, last_mtime, rss_start = [], None, None
            start = time.monotonic()
            published = 0
            while published < n:
                elapsed = time.monotonic() - start
                due = min(n, int(elapsed * rate))
                while published < due:
                    now = node.get_clock().now().nanoseconds * 1e-9
                    command = JointState(name=names, position=[float(v) for v in session.actions[published]])
                    command.header.stamp = conversions.stamp_from_seconds(now)
                    commands.publish(command)
                    observations.publish(conversions.marker_poses_msg(now + 0.0002, "camera",
                                                                      session.observations[published]))
                    published += 1
                executor.spin_once(timeout_sec=0.0)
                mtime = checkpoint.stat().st_mtime if checkpoint.exists() else None
                if mtime is not None and mtime != last_mtime:
                    checkpoint_writes.append(time.monotonic())
                    last_mtime = mtime
                if rss_start is None and elapsed > 5.0:
                    rss_start = _rss_mb(process.process.pid)
            rss_end = _rss_mb(process.process.pid)
            end = time.monotonic()
            settle = end + 5.0  # the last diagnostics: counts after the node took in everything
            while time.monotonic() < settle:
                executor.spin_once(timeout_sec=0.05)
            alive = process.running()
        finally:
            if process is not None:
                process.stop()

    def gaps(times, until):
        times = [t for t in times if start <= t <= until]
        return float(np.max(np.diff([start, *times, until]))) if times else float(until - start)

    received = int(last.get("received.command", 0)) + int(last.get("received.observations", 0))
    lost = int(last.get("lost.command_messages", 0)) + int(last.get("lost.observations_messages", 0))
    counts = {k: int(v) for k, v in last.items() if k.startswith(("rejected.", "shed.", "received.", "lost."))}
    return {
        "rate_hz": rate, "seconds": seconds, "max_sample_age_s": max_sample_age, "published_messages": 2 * n,
        "node_alive": alive,
        "diagnostics_max_gap_s": gaps(diagnostics, end),
        "checkpoint_max_gap_s": gaps(checkpoint_writes, end),
        "prediction_latency_p99_ms": float(1e3 * np.percentile(latencies, 99)) if latencies else float("nan"),
        "prediction_latency_median_ms": float(1e3 * np.median(latencies)) if latencies else float("nan"),
        "rss_growth_mb": float(rss_end - rss_start) if rss_start is not None else float("nan"),
        "uncounted_drops": 2 * n - received - lost, "lost_in_dds": lost,
        "samples_learnt": int(last.get("step", 0)), "pending_samples": int(last.get("pending_samples", 0)),
        "counts": counts,
    }


def _table(result):
    lines = [f"scheme_node at {result['rate_hz']:.0f} pairs/s for {result['seconds']:.0f} s "
             f"({result['published_messages']} messages, max_sample_age {result['max_sample_age_s']} s; node alive: "
             f"{result['node_alive']})"]
    for key, (op, target) in TARGETS.items():
        value = result[key]
        ok = value <= target if op == "<=" else value >= target
        lines.append(f"  {key:<28s} {value:>10.3f}   target {op} {target}   {'ok' if ok else 'MISSED'}")
    lines.append(f"  learnt {result['samples_learnt']}, pending {result['pending_samples']}; counts {result['counts']}")
    return "\n".join(lines)


@command
def main(argv=None):
    """Console entry point: run, print the table, write the JSON file."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.load_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=1000.0, help="pairs per second (default: %(default)s)")
    parser.add_argument("--seconds", type=float, default=60.0, help="duration (default: %(default)s)")
    parser.add_argument("--max-sample-age", type=float, default=0.05,
                        help="scheme_node's max_sample_age, s (default: %(default)s, a live setting)")
    parser.add_argument("--out", default=os.path.join("out", "bench", "load.json"), help="JSON file to write")
    args = parser.parse_args(argv)
    result = run_load(args.rate, args.seconds, args.max_sample_age)
    return report(result, _table(result), args.out)


if __name__ == "__main__":
    raise SystemExit(main())
