"""What scheme_node reports on /diagnostics (scheme_diagnostics.py), without DDS."""

from collections import Counter

from diagnostic_msgs.msg import DiagnosticStatus

from body_scheme_core.learning import BodySchemeLearner
from body_scheme_core.world import make_session, planar_2dof
from body_scheme_nodes import scheme_diagnostics


def _learner(steps):
    tree = planar_2dof()
    session = make_session(tree, steps, 0)
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions)
    for t in range(steps):
        learner.update(session.actions[t], session.observations[t])
    return learner


def test_the_level_says_warn_without_a_scheme_ok_when_valid_and_error_when_learning_stalls():
    fresh, learnt = _learner(1), _learner(80)
    assert scheme_diagnostics.scheme_level(fresh, [], None)[0] == DiagnosticStatus.WARN
    edges = learnt.edge_status()
    assert scheme_diagnostics.scheme_level(learnt, edges, None) == (DiagnosticStatus.OK, "body scheme valid (steady)")
    level, message = scheme_diagnostics.scheme_level(learnt, edges, 12.0)
    assert level == DiagnosticStatus.ERROR and "nothing learnt for 12 s" in message
    invalid = [dict(edges[0], valid=False)] + edges[1:]
    assert scheme_diagnostics.scheme_level(learnt, invalid, None)[0] == DiagnosticStatus.ERROR


def test_values_counters_and_one_status_per_edge():
    learner = _learner(80)
    edges = learner.edge_status()
    values = scheme_diagnostics.learner_values(learner, edges, [0.002, 0.001, 0.003], [])
    assert values["step"] == 80 and values["edges"] == len(edges) and values["update_latency_median_ms"] == 2.0
    assert scheme_diagnostics.counter_values({"rejected": Counter(b=2, a=1), "shed": {}}) == {"rejected.a": 1,
                                                                                              "rejected.b": 2}
    mismatch = [dict(edges[0], in_mismatch=True)] + edges[1:]
    statuses = scheme_diagnostics.edge_statuses("/n", mismatch, "hw")
    assert [s.message for s in statuses] == ["mismatch"] + ["valid"] * (len(edges) - 1)
    assert statuses[0].name == f"/n: local model {edges[0]['parent']}->{edges[0]['child']}"
