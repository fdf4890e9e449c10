"""What scheme_node reports on /diagnostics: the body scheme's status, its counters, and one status per local model.

Pure functions of the learner and the node's counters (no rclpy node), so the rules are tested without DDS:
WARN while there is no body scheme or it is not trusted, ERROR while a local model is invalid or commands arrive
without learning (``stall_timeout``), else OK.
"""

from __future__ import annotations

import math

from diagnostic_msgs.msg import DiagnosticStatus

from . import conversions

__all__ = ["status_name", "scheme_level", "learner_values", "counter_values", "edge_statuses"]


def status_name(node_name):
    """The name of scheme_node ``node_name``'s (fully qualified: ``/robot2/scheme_node``) body scheme status: what
    babble_node's ``watch_diagnostics`` matches exactly."""
    return f"{node_name}: body scheme"


def scheme_level(learner, edges, stalled_for):
    """``(level, message)`` of the body scheme's status; ``stalled_for``: seconds without learning while commands
    arrive, or None."""
    n_invalid = sum(not e["valid"] for e in edges)
    if learner.body_scheme is None:
        level, message = DiagnosticStatus.WARN, f"no body scheme yet ({learner.phase}, step {learner.step})"
    elif n_invalid:
        level, message = DiagnosticStatus.ERROR, f"{n_invalid} local model(s) invalid ({learner.phase})"
    elif learner.unexplained_parts:
        level, message = DiagnosticStatus.WARN, (f"not trusted: the body scheme does not explain part(s) "
                                                 f"{list(learner.unexplained_parts)} ({learner.phase})")
    else:
        level, message = DiagnosticStatus.OK, f"body scheme valid ({learner.phase})"
    if stalled_for is not None:
        level, message = DiagnosticStatus.ERROR, (f"commands arriving but nothing learnt for {stalled_for:.0f} s "
                                                  f"(see rejected.*): {message}")
    return level, message


def learner_values(learner, edges, latency, lag):
    """The learner's figures: phase, step, edges, trust, the noise estimate, candidates; the update latency and the
    learning lag (s, recent values) as median/max in ms."""
    latency = sorted(latency)
    lateral, depth, rotation = learner.noise.axis_sigmas()
    return {"phase": learner.phase, "step": learner.step, "edges": len(edges),
            "invalid_edges": sum(not e["valid"] for e in edges),
            "trusted": learner.trusted, "unexplained_parts": list(learner.unexplained_parts),
            "noise.trans_mm": 1e3 * learner.noise.sigma_trans,
            "noise.rot_deg": math.degrees(learner.noise.sigma_rot),
            "noise.lateral_mm": 1e3 * lateral, "noise.depth_mm": 1e3 * depth,
            "noise.rotation_deg": math.degrees(rotation), "noise.residuals": learner.noise.n_observations,
            "noise.detection_scale_position": learner.noise.detection_scale[0],
            "noise.detection_scale_rotation": learner.noise.detection_scale[1],
            "noise.detections": learner.noise.n_detected,
            "update_latency_median_ms": 1e3 * latency[len(latency) // 2] if latency else float("nan"),
            "update_latency_max_ms": 1e3 * latency[-1] if latency else float("nan"),
            "learning_lag_ms": 1e3 * lag[-1] if lag else float("nan"),
            "learning_lag_max_ms": 1e3 * max(lag) if lag else float("nan"),
            "candidates": learner.n_candidates, "candidates_raced": learner.n_raced}


def counter_values(counters):
    """``{"prefix.key": count}`` of ``{prefix: Counter}``, keys sorted (``rejected``, ``events``, ``shed``, ...)."""
    return {f"{prefix}.{key}": count for prefix, counter in counters.items() for key, count in sorted(counter.items())}


def edge_statuses(name, edges, hardware_id):
    """One ``DiagnosticStatus`` per tree edge (:meth:`BodySchemeLearner.edge_status` entries): OK when valid, ERROR
    in mismatch or invalid."""
    statuses = []
    for e in edges:
        level = DiagnosticStatus.ERROR if e["in_mismatch"] or not e["valid"] else DiagnosticStatus.OK
        message = "valid" if level == DiagnosticStatus.OK else ("mismatch" if e["in_mismatch"] else "invalid")
        statuses.append(conversions.diagnostic_status(
            f"{name}: local model {e['parent']}->{e['child']}", level, message,
            {k: e[k] for k in ("model", "kind", "n_test", "trans_error", "rot_error", "theta_trans", "theta_rot")},
            hardware_id))
    return statuses
