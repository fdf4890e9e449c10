"""``fuzz``: scheme_node, control_node and babble_node under hostile input over DDS, every message accounted for.

    python -m body_scheme_apps.fuzz [--messages 10000] [--steps 600] [--seed 0] [--out out/fuzz/fuzz.json]

The installed scheme_node runs as its own process in this process's ROS domain (``ROS_DOMAIN_ID``). This process
publishes a babbling session of the 2-DOF arm (a valid command and its observation every ``PERIOD`` s) and, in the
gaps, hostile messages of every kind (:data:`.fuzz_plan.CASES`): NaN, inf and 1e300 in positions and joint values, zero,
NaN and non-unit quaternions, empty and mismatched arrays, unknown, negative, repeated and duplicate ids and joint
names, stamps in the future, in the past, zero and going backwards, and bursts of them. The valid traffic's ignored
fields (JointState velocity and effort, pose covariances) carry NaN, inf and 1e300 too.

The other inputs of the graph get their share (:data:`.fuzz_plan.OTHER_INPUTS`): requests to explore near a posture and
CameraInfos that no camera could have (scheme_node, with exploration on), IK targets that control_node must refuse
(NaN, unknown parts, other frames; its commands remapped away from scheme_node's), and joint states 50 rad or 1e308
beyond the limits, malformed or too large (babble_node, paused), each with messages too large to read.

Every hostile message is built so that the node's reaction is certain, and the plan adds up what each node must
count (``rejected.*``, ``restamped.*``, the learning steps, the driver's ``joint_states_*``, control_node's answers).
The run passes when the nodes are alive, every message sent was taken, lost in DDS (counted) or refused unread
(counted) (received + lost + refused = sent), the counts are exactly the plan's with nothing else refused or shed,
every IK target taken was answered, and scheme_node learnt the same tree (pairs and model kinds) as the same settings
learn in-process from the valid samples alone. Figures: printed, and written as JSON (``ok``, ``published_messages``,
``hostile_messages``, ``expected``, ``counted``, ``differences``, ``other_nodes``, ``structure``,
``baseline_structure``, ``diagnostics_max_gap_s`` per node).
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
import tempfile
import time
from collections import Counter

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState

from body_scheme_apps.bench_output import report
from body_scheme_apps.live_demo import domain_id
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_msgs.msg import BodySchemeStructure, IKResult, MarkerPoses
from body_scheme_nodes import conversions
from body_scheme_nodes.graph import NodeProcess, monitor_node
from body_scheme_nodes.message_feed import MESSAGE_KINDS
from body_scheme_nodes.qos import LATCHED
from body_scheme_nodes.settings import SchemeSettings

from .entry import command
from .fuzz_plan import CASES, OTHER_MAX_BYTES, OTHER_TOPICS, PERIOD, Plan, make_plan

__all__ = ["PERIOD", "CASES", "Plan", "make_plan", "run_fuzz", "main"]

# ---------------------------------------------------------------------- the run
def fuzz_parameters(tree):
    """scheme_node's parameters for the run; the in-process baseline learns with the same settings."""
    return {"part_ids": [int(i) for i in tree.marker_ids], "joint_names": list(tree.action_joint_names),
            "action_lower": [float(v) for v in tree.action_lower],
            "action_upper": [float(v) for v in tree.action_upper],
            "pairing_grace": 0.2, "learner.train_window": 20,
            # Nothing may be shed for load here: the count must be exact, however slow the machine.
            "max_sample_age": 600.0, "max_pending_samples": 100000, "max_inbox": 100000,
            # Exploration on, so that its requests and CameraInfos are read (it changes nothing the learner does).
            "exploration": True, "exploration_candidates": 8, "exploration_camera_info": "camera/camera_info",
            "max_message_bytes": OTHER_MAX_BYTES}


def other_nodes(tree):
    """``{name: (parameters, ros_args)}`` of control_node and babble_node in the run: paused or answering only, their
    commands remapped away from scheme_node's."""
    return {
        "control_node": ({"part_id": int(max(tree.marker_ids)), "max_message_bytes": OTHER_MAX_BYTES},
                         ("-r", "joint_commands:=/fuzz/control_node/joint_commands")),
        "babble_node": ({"robot": "planar_2dof", "start_paused": True, "collision_check": False,
                         "watch_diagnostics": "", "camera_timeout": 0.0, "joint_state_timeout": 0.0,
                         "max_message_bytes": OTHER_MAX_BYTES},
                        ("-r", "joint_commands:=/fuzz/babble_node/joint_commands")),
    }


#: Each other node's counters that add up to the messages sent to it: taken (by kind), lost in DDS, refused unread.
ACCOUNTS = {"control_node": ("received", "lost.ik_target_messages", "rejected.oversized_message"),
            "babble_node": ("driver.joint_states", "driver.joint_states_rejected", "driver.joint_states_out_of_range",
                            "driver.joint_states_oversized", "driver.joint_states_lost")}
STATUS = {"scheme_node": "/scheme_node: body scheme", "control_node": "/control_node: control",
          "babble_node": "/babble_node: babbling"}


def baseline_structure(settings, samples):
    """Edges ``(parent, child, kind)`` the node's settings learn in-process from ``samples`` alone."""
    learner = settings.new_learner()
    for actions, observations in samples:
        learner.update(actions, observations)
    return sorted((e["parent"], e["child"], e["kind"]) for e in learner.edge_status())


def run_fuzz(n_messages=3000, n_steps=300, seed=0, domain=None, env=None, log_dir=None, timeout=120.0):
    """Run the fuzz and return the report (a dict; ``ok`` says whether it passed)."""
    tree = planar_2dof()
    session = make_session(tree, n_steps, seed=seed, sigma_trans=0.02, sigma_rot=math.radians(5.0), visibility=0.9)
    plan = make_plan(session, n_messages, seed)
    parameters = fuzz_parameters(tree)
    baseline = baseline_structure(SchemeSettings.from_parameters(parameters), plan.valid_samples)
    domain = domain_id(env) if domain is None else domain
    with tempfile.TemporaryDirectory() as tmp, monitor_node("fuzz", domain) as (node, executor):
        processes = {}
        statuses = {name: {} for name in STATUS}
        arrivals = {name: [] for name in STATUS}
        last, structure, answers = statuses["scheme_node"], [], []

        def on_diagnostics(msg):
            for name, status_name in STATUS.items():
                for status in msg.status:
                    if status.name == status_name:
                        arrivals[name].append(conversions.seconds_from_stamp(msg.header.stamp))  # the node's clock
                        statuses[name].clear()
                        statuses[name].update({kv.key: kv.value for kv in status.values})

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)
        node.create_subscription(BodySchemeStructure, "body_scheme/structure", structure.append, LATCHED)
        node.create_subscription(IKResult, "ik_result", answers.append, 10000)
        publishers = {"command": node.create_publisher(JointState, "joint_commands", 1000),
                      "observations": node.create_publisher(MarkerPoses, "observations", 1000)}
        publishers.update({topic: node.create_publisher(msg_type, name, 1000)
                           for topic, (msg_type, name, _) in OTHER_TOPICS.items()})
        published = Counter()
        try:  # every node started is stopped, whatever comes (an interrupt too)
            processes["scheme_node"] = NodeProcess("body_scheme_nodes", "scheme_node", parameters, log_dir or tmp,
                                                   env=env)
            for name, (node_parameters, ros_args) in other_nodes(tree).items():
                processes[name] = NodeProcess("body_scheme_nodes", name, node_parameters, log_dir or tmp, env=env,
                                              ros_args=ros_args)
            deadline = time.monotonic() + 60
            while not (all(statuses.values()) and structure and publishers["camera_info"].get_subscription_count()
                       and all(p.get_subscription_count() for p in publishers.values())) \
                    and time.monotonic() < deadline:  # up and discovered
                executor.spin_once(timeout_sec=0.05)
            if not (all(statuses.values()) and structure):
                raise RuntimeError("the nodes did not come up within 60 s:\n" + "\n".join(
                    p.output()[-2000:] for p in processes.values()))
            t0 = node.get_clock().now().nanoseconds * 1e-9 + 0.2
            start = time.monotonic() + 0.2
            for times in arrivals.values():
                del times[:-1]
            for offset, kind, build in plan.messages:  # kind: a message kind of scheme_node or an OTHER_TOPICS key
                while time.monotonic() < start + offset:
                    executor.spin_once(timeout_sec=max(0.0, min(0.005, start + offset - time.monotonic())))
                publishers[kind].publish(build(t0))
                published[kind] += 1
                start += max(0.0, time.monotonic() - (start + offset) - 0.5)  # a 352 MB publish: the rest follows

            def done():
                return (int(last.get("step", -1)) >= plan.learning_steps
                        and all(int(last.get(k, 0)) >= v for k, v in plan.expected.items())
                        and all(int(last.get(f"received.{k}", 0)) >= published[k] for k in MESSAGE_KINDS)
                        and all(sum(int(statuses[n].get(k, 0)) for k in keys) >= published[_topic_of(n)]
                                for n, keys in ACCOUNTS.items())
                        and len(answers) >= int(statuses["control_node"].get("received", 0)))

            deadline = time.monotonic() + timeout
            while not done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
            settle = time.monotonic() + 2.5  # one more diagnostics message: nothing else arrives late
            while time.monotonic() < settle:
                executor.spin_once(timeout_sec=0.1)
            alive = {name: p.running() for name, p in processes.items()}
            gaps = {name: float(np.diff(times).max(initial=0.0)) for name, times in arrivals.items()}  # node clocks
            # The same before the messages of hundreds of MB (rclpy's take of one holds a node for seconds).
            huge_from = t0 + plan.huge_from
            gaps_before = {name: float(np.diff([t for t in times if t < huge_from]).max(initial=0.0))
                           for name, times in arrivals.items()}
        finally:
            for p in processes.values():
                p.stop()
            output = "\n".join(f"----- {name} -----\n{p.output()[-3000:]}" for name, p in processes.items())

    counted = {k: int(v) for k, v in last.items() if k.startswith(("rejected.", "restamped.", "shed."))
               and k != "rejected_total" and int(v)}
    expected = dict(plan.expected)
    differences = {k: {"expected": expected.get(k, 0), "counted": counted.get(k, 0)}
                   for k in sorted(set(expected) | set(counted)) if expected.get(k, 0) != counted.get(k, 0)}
    received = {k: int(last.get(f"received.{k}", 0)) for k in MESSAGE_KINDS}
    # scheme_node's requests: each taken (and answered, exploration.near_requests), none lost.
    explore_requests = int(last.get("exploration.near_requests", 0)) + int(last.get("lost.explore_near_messages", 0))
    received["explore_near"] = explore_requests + plan.cases["explore_near_too_large"]
    other = {name: _other_node_report(name, statuses[name], plan.other_expected[name], published[_topic_of(name)])
             for name in ACCOUNTS}
    other["control_node"]["answered"] = len(answers)
    answered_all = len(answers) == int(statuses["control_node"].get("received", -1))
    learnt = sorted((e.parent_id, e.child_id, e.kind) for e in structure[-1].edges) if structure else []
    result = {
        "ok": bool(all(alive.values()) and not differences and received == {k: published[k] for k in received}
                   and int(last.get("lost.explore_near_messages", 0)) == 0 and learnt == baseline
                   and int(last.get("step", -1)) == plan.learning_steps and answered_all
                   and all(not accounts["differences"] for accounts in other.values())),
        "node_alive": all(alive.values()), "nodes_alive": alive, "published_messages": sum(published.values()),
        "hostile_messages": sum(plan.cases.values()), "published": dict(published), "received": received,
        "learning_steps": {"expected": plan.learning_steps, "counted": int(last.get("step", -1))},
        "expected": expected, "counted": counted, "differences": differences, "other_nodes": other,
        "structure": [list(e) for e in learnt], "baseline_structure": [list(e) for e in baseline],
        "diagnostics_max_gap_s": gaps["scheme_node"], "diagnostics_max_gap_s_by_node": gaps,
        "diagnostics_max_gap_s_before_huge_messages": gaps_before,
        "cases": dict(sorted(plan.cases.items())),
    }
    if not result["ok"]:
        result["node_output_tail"] = output[-9000:]
    return result


def _topic_of(node_name):
    return next(topic for topic, (_, _, name) in OTHER_TOPICS.items() if name == node_name)


def _other_node_report(name, status, expected, sent):
    """control_node's or babble_node's accounts: what it counted of each expected counter, what it took, lost and
    refused unread, and the differences from the plan (none lost: the plan's figures are exact)."""
    keys = ACCOUNTS[name]
    counted = {k: int(status.get(k, 0)) for k in sorted(set(expected) | set(keys))}
    differences = {k: {"expected": expected.get(k, 0), "counted": counted[k]} for k in counted
                   if counted[k] != expected.get(k, 0)}
    accounted = sum(counted[k] for k in keys)
    if accounted != sent:
        differences["sent"] = {"expected": sent, "counted": accounted}
    return {"sent": sent, "counted": counted, "differences": differences}


def _table(result):
    lines = [f"fuzz: {result['published_messages']} messages, {result['hostile_messages']} hostile "
             f"({len(result['cases'])} kinds); nodes alive: {result['nodes_alive']}",
             f"  scheme_node received {result['received']} of {result['published']}",
             "  learning steps {counted} (expected {expected})".format(**result["learning_steps"]),
             f"  counts {'exact' if not result['differences'] else 'DIFFER: ' + str(result['differences'])}",
             f"  structure {result['structure']} (without fuzz: {result['baseline_structure']})"]
    for name, accounts in result["other_nodes"].items():
        state = "exact" if not accounts["differences"] else f"DIFFER: {accounts['differences']}"
        lines.append(f"  {name}: sent {accounts['sent']}, counted {accounts['counted']}: {state}")
    gaps = ", ".join(f"{n} {g:.2f} s" for n, g in result["diagnostics_max_gap_s_by_node"].items())
    before = ", ".join(f"{n} {g:.2f} s" for n, g in result["diagnostics_max_gap_s_before_huge_messages"].items())
    lines += [f"  /diagnostics max gap {gaps} (target <= 2); before the messages of hundreds of MB {before}",
              f"  {'PASSED' if result['ok'] else 'FAILED'}"]
    return "\n".join(lines)


@command
def main(argv=None):
    """Console entry point: run, print, write the JSON file; exit code 1 if the run failed."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.fuzz", description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=10000, help="messages in all (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=600, help="valid samples (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=os.path.join("out", "fuzz", "fuzz.json"), help="JSON file to write")
    args = parser.parse_args(argv)
    result = run_fuzz(args.messages, args.steps, args.seed, log_dir=pathlib.Path(args.out).parent)
    status = report(result, _table(result), args.out)
    return status or (0 if result["ok"] else 1)


if __name__ == "__main__":
    raise SystemExit(main())
