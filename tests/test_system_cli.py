"""System tests of the ``body-scheme`` command: the installed executable, as a user runs it, against real node
processes over DDS. One test per node whose services it calls; each subcommand is run at least once."""

from __future__ import annotations

import signal
import subprocess

import numpy as np
import pytest
from scheme_feed import Babbler, Collector, learned_the_tree, scheme_parameters
from urdf_parser_py.urdf import URDF

from body_scheme_core.world import make_session, planar_2dof
from body_scheme_nodes.graph import executable

pytestmark = pytest.mark.system

CLI = str(executable("body_scheme_nodes", "body-scheme"))


@pytest.fixture
def cli(ros_env):
    """``cli(*args)``: run ``body-scheme args`` in this test's domain; a CompletedProcess (text). Its ``--timeout``
    is 120 s unless given: the command itself waits for the node's services, however busy the machine."""

    def run(*args):
        timeout = () if "--timeout" in args else ("--timeout", "120")
        return subprocess.run([CLI, *args, *timeout], env=ros_env, capture_output=True, text=True, timeout=300,
                              check=False)

    return run


def test_status_events_state_urdf_and_params_of_scheme_node(start_node, ros_node, spin_until, cli, ros_env,
                                                            tmp_path):
    tree = planar_2dof()
    session = make_session(tree, n_steps=300, seed=0, sigma_trans=0.02, sigma_rot=np.radians(5.0), visibility=0.95)
    state_dir = tmp_path / "state"
    process = start_node("body_scheme_nodes", "scheme_node", dict(scheme_parameters(tree), state_dir=str(state_dir)))
    collector = Collector(ros_node)
    assert spin_until(lambda: collector.structure is not None, timeout=60), process.output()

    answer = cli("get-urdf")
    assert answer.returncode == 1 and "no body scheme yet" in answer.stderr, answer
    answer = cli("status", "--node", "/scheme_node", "--brief")
    assert answer.returncode == 0, answer
    assert answer.stdout.startswith("WARN  /scheme_node: body scheme: no body scheme yet"), answer.stdout

    babbler = Babbler(ros_node, session)
    true_edges = {frozenset(edge) for edge in tree.marker_tree_edges()}
    assert spin_until(lambda: learned_the_tree(collector, true_edges), timeout=90, during=babbler), process.output()
    events_log = tmp_path / "events.txt"  # followed after the fact: the latest events are kept for late followers
    with events_log.open("w") as out:
        events = subprocess.Popen([CLI, "events", "--node", "scheme_node", "--timeout", "120"], env=ros_env,
                                  stdout=out, stderr=subprocess.PIPE, text=True)  # the name without its slash
    assert spin_until(lambda: "structure_found" in events_log.read_text(), timeout=60), events_log.read_text()
    events.send_signal(signal.SIGINT)  # Ctrl-C ends it quietly
    assert events.wait(timeout=30) == 0, events.stderr.read()
    first = events_log.read_text().splitlines()[0]
    assert first.startswith("step ") and "structure_found" in events_log.read_text(), first

    answer = cli("status", "--node", "scheme_node")
    assert answer.returncode == 0, answer
    lines = answer.stdout.splitlines()
    assert any(line.startswith(("OK    /scheme_node: body scheme:", "WARN  /scheme_node: body scheme:"))
               for line in lines), lines
    assert sum(": local model " in line for line in lines) == len(true_edges), lines
    assert "      phase: " in answer.stdout and "      step: " in answer.stdout

    answer = cli("get-urdf", "--out", str(tmp_path / "learned.urdf"))
    assert answer.returncode == 0 and "learned body scheme at step" in answer.stderr, answer
    robot = URDF.from_xml_string((tmp_path / "learned.urdf").read_text())
    assert sum(joint.type != "fixed" for joint in robot.joints) == len(tree.action_joint_names)

    answer = cli("save", "mine.json")
    assert answer.returncode == 0 and answer.stdout.startswith("saved step"), answer
    assert (state_dir / "mine.json").is_file()
    assert cli("reset").returncode == 0
    answer = cli("get-urdf")
    assert answer.returncode == 1 and "no body scheme yet" in answer.stderr, answer
    answer = cli("load", "mine.json")
    assert answer.returncode == 0 and answer.stdout.startswith("loaded step"), answer
    assert cli("get-urdf").returncode == 0
    answer = cli("load", "../outside.json")
    assert answer.returncode == 1 and answer.stderr.startswith("load failed"), answer

    answer = cli("params", "/scheme_node")
    assert answer.returncode == 0 and "part_ids: [1, 2, 3]" in answer.stdout.splitlines(), answer
    answer = cli("params", "/scheme_node", "joint_names")
    assert answer.returncode == 0 and answer.stdout.strip() == "joint_names: [joint1, joint2]", answer
    answer = cli("params", "/scheme_node", "update_period", "0.5")
    assert answer.returncode == 1 and "read at start-up only" in answer.stderr, answer
    answer = cli("params", "/scheme_node", "no_such_parameter")
    assert answer.returncode == 1 and "has no parameter no_such_parameter" in answer.stderr, answer


def test_pause_resume_stop_and_params_of_babble_node_and_a_node_that_is_not_there(start_node, cli, ros_env,
                                                                                   ros_node, spin_until):
    babble = start_node("body_scheme_nodes", "babble_node", {"robot": "arm_4dof", "max_velocity": 0.5})
    answer = cli("pause")
    assert answer.returncode == 0 and answer.stdout.strip() == "paused after the current move", (
        answer, babble.output())
    answer = cli("resume")
    assert answer.returncode == 0 and answer.stdout.strip() == "resumed (was paused)", answer
    answer = cli("stop")
    assert answer.returncode == 0 and answer.stdout.startswith("stopped"), answer
    answer = cli("pause")
    assert answer.returncode == 1 and "resume first" in answer.stderr, answer
    answer = cli("params", "/babble_node", "max_velocity", "0.25")
    assert answer.returncode == 1 and "restart babble_node" in answer.stderr, answer  # never silently ignored
    assert cli("params", "/babble_node", "max_velocity").stdout.strip() == "max_velocity: 0.5"
    answer = cli("status", "--brief")  # every node's statuses: here babble_node's
    assert answer.returncode == 0 and "/babble_node: babbling" in answer.stdout, answer

    for args in (("pause", "--node", "/nobody"), ("params", "nobody"), ("status", "--node", "/nobody"),
                 ("events", "--node", "/nobody")):
        answer = cli(*args, "--timeout", "2")
        assert answer.returncode == 2 and "running, in this ROS_DOMAIN_ID" in answer.stderr, (args, answer)
    waiting = subprocess.Popen([CLI, "save", "--node", "/nobody", "--timeout", "300"], env=ros_env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert spin_until(lambda: "body_scheme_cli" in ros_node.get_node_names(), timeout=60)
    waiting.send_signal(signal.SIGINT)  # Ctrl-C while it waits: cut short, not done
    assert waiting.wait(timeout=30) == 130, waiting.communicate()


def _event(step):
    from body_scheme_msgs.msg import SchemeEvent

    return SchemeEvent(step=step, kind="model_sampled", reason=f"event {step}", parent_id=-1, child_id=-1,
                       trans_error=float("nan"), rot_error=float("nan"))


def _follow(ros_env, node, *args):
    """``body-scheme events --node NODE --count 1 ARGS`` started, once it says it follows (its stderr's first line)."""
    process = subprocess.Popen([CLI, "events", "--node", node, "--count", "1", "--timeout", "120", *args],
                               env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert process.stderr.readline().startswith("following "), process.communicate(timeout=30)
    return process


def test_events_follows_what_comes_new_skips_what_is_kept_and_a_played_bag_is_followed_too(ros_env, ros_node,
                                                                                           spin_until):
    """``--new`` prints what comes, not what the publisher kept; a publisher that keeps nothing (a bag played back,
    volatile) is followed too (a transient local subscription would never be matched with it)."""
    from body_scheme_nodes.qos import RECENT_EVENTS

    for namespace, qos, args in (("/kept", RECENT_EVENTS, ("--new",)), ("/played", 100, ())):
        publisher = ros_node.create_publisher(_event(0).__class__, f"{namespace}/body_scheme/events", qos)
        publisher.publish(_event(1))  # before the follower: kept by /kept, gone for /played
        follower = _follow(ros_env, f"{namespace}/scheme_node", *args)
        steps = iter(range(100, 10**6))  # published until one arrives, however long matching takes
        assert spin_until(lambda p=publisher, f=follower, s=steps: p.publish(_event(next(s))) or f.poll() is not None,
                          timeout=60), namespace
        out, err = follower.communicate(timeout=30)
        assert follower.returncode == 0 and out.count("\n") == 1, (namespace, out, err)
        assert out.startswith("step ") and int(out.split()[1]) >= 100, (namespace, out)  # not the kept event 1
