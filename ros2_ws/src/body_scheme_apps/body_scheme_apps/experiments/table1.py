"""Table I and Fig. 6 of the paper (Sec. IV-B, IV-C): how fast the 6-DOF arm's body scheme recovers from a change.

Protocol (the paper's): :func:`~body_scheme_core.world.powercube_6dof`, 7 markers, the learner starts from the
engineered body scheme (the robot's specification) and babbles through 4 blocks of 100 samples: normal; changed
(end-effector joint blocked at 0.8 rad, or the tool displaced 0.1 m and bent 45 deg); repaired; the same change again.
Noise mode: the paper's noise (44 mm / 15 deg) and visibility (91.9 % blocked, 79.0 % deformed) from
:mod:`body_scheme_core.world`; rendered mode: the simulator's camera images through the ArUco tracker
(:func:`body_scheme_sim.sessions.record_protocol`), the learner with the tracker's noise sigmas.

Recovery time, two definitions:

- ``recovery`` (ours, since issue 6): the number of samples of the changed body whose end-effector prediction came from
  the outdated body scheme, ``s - t0 + 1``, where ``t0`` is the first sample of the block (the change) and ``s`` the
  sample whose update raised the first ``model_replaced`` or ``model_reinstated`` event on the end-effector edge (the
  tree edge into marker 7) in the block. Predictions are made before each update, so samples ``t0 .. s`` were
  predicted with the old model and the minimum is 1. A run without such an event in the block counts the whole block
  (100) and is reported as not recovered.
- ``invalid`` (the paper's likely one: samples without a valid spanning tree): the number of samples of the block after
  whose update some edge of the body scheme was invalid (test window) or in mismatch. A change recognised before the
  failed model's window turns invalid counts 0, as the paper's 0.45 and 0.65 suggest it did there.
"""

from __future__ import annotations

import numpy as np

from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.models import engineered_models
from body_scheme_core.world import joint_blocked_protocol, limb_deformed_protocol, powercube_6dof

__all__ = ["FIGURES", "PAPER", "TARGETS", "NOTES", "PROTOCOLS", "run", "run_protocol", "recovery_times", "plot"]

#: Experiment name -> results.json key prefix.
PROTOCOLS = {"joint_blocked": "blocked", "limb_deformed": "deformed"}
N_PER_BLOCK = 100
_DEFINITION = ("samples of the changed body predicted with the outdated body scheme: s - t0 + 1, s = sample whose "
               "update replaced or reinstated the end-effector model (minimum 1; no adaptation in the block = 100)")
FIGURES = {}
for _name, _prefix in PROTOCOLS.items():
    _what = "joint blocked" if _prefix == "blocked" else "limb deformed"
    FIGURES.update({
        f"{_prefix}_recovery_failure": f"{_what}, block 2 (first change): {_DEFINITION}",
        f"{_prefix}_recovery_repair": f"{_what}, block 3 (repaired): {_DEFINITION}",
        f"{_prefix}_recovery_same": f"{_what}, block 4 (the same change again): {_DEFINITION}",
        f"{_prefix}_invalid_failure": f"{_what}, block 2: samples after whose update an edge of the body scheme was "
                                      "invalid or in mismatch (the paper's likely definition)",
        f"{_prefix}_invalid_repair": f"{_what}, block 3: the same",
        f"{_prefix}_invalid_same": f"{_what}, block 4: the same",
        f"{_prefix}_ee_err_mm_after": f"{_what}: mean end-effector position error (mm, prediction made before the "
                                      "sample vs ground truth) in block 2 after recovery (samples s+1 .. 199)",
        f"{_prefix}_ee_err_mm_before": f"{_what}: the same in block 1 (engineered body scheme, healthy arm)",
        f"{_prefix}_all_err_mm_after": f"{_what}: like ee_err_mm_after, averaged over every part but the root",
        f"{_prefix}_not_recovered": f"{_what}: blocks 2-4 without an adaptation event (count per run)",
    })
#: The paper's Table I and Sec. IV-B/C (recovery in samples; errors in mm).
PAPER = {"blocked_recovery_failure": 16.50, "blocked_recovery_repair": 0.45, "blocked_recovery_same": 0.65,
         "blocked_ee_err_mm_after": 51.0, "blocked_ee_err_mm_before": 37.0,
         "deformed_recovery_failure": 20.20, "deformed_recovery_repair": 11.10, "deformed_recovery_same": 12.10,
         "deformed_ee_err_mm_after": 47.0}
#: The issue's targets (all: lower is better): no recovery time worse than before the rigid joints and the joint
#: fit (the GP-only learner's figures of docs/RESULTS.md at commit 62a5438), and the end effector within 20 mm after
#: recovery.
TARGETS = {"blocked_recovery_failure": 7.05, "blocked_recovery_repair": 3.30, "blocked_recovery_same": 3.85,
           "blocked_ee_err_mm_after": 20.0, "deformed_recovery_failure": 13.5, "deformed_recovery_repair": 3.60,
           "deformed_recovery_same": 3.60, "deformed_ee_err_mm_after": 20.0}
NOTES = """\
The earlier targets of 0.5 samples for a repair and for the same change again (the paper's 0.45 and 0.65) cannot be
met under the first definition, whose floor is 1 sample; the second definition is the one to compare with the paper.
"""
_ADAPTED = ("model_replaced", "model_reinstated")


def _session(protocol, seed, perception):
    if perception == "noise":
        protocol_session = joint_blocked_protocol if protocol == "joint_blocked" else limb_deformed_protocol
        return protocol_session(seed, n_per_block=N_PER_BLOCK)
    if perception == "rendered":
        from body_scheme_sim.sessions import record_protocol
        return record_protocol(protocol, seed, n_per_block=N_PER_BLOCK, perception="rendered")
    raise ValueError(f"perception must be 'noise' or 'rendered', got {perception!r}")


def _config(perception):
    if perception == "rendered":
        from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS
        return BodySchemeConfig(sigma_trans=RENDERED_SIGMA_TRANS, sigma_rot=RENDERED_SIGMA_ROT)
    return BodySchemeConfig()


def recovery_times(events, change_steps, n_steps, effector):
    """Recovery time (samples, see the module docstring) after each change, and whether it was reached.

    Parameters
    ----------
    events : list of Event
    change_steps : list of int
        First sample of each changed block, ascending.
    n_steps : int
    effector : int
        End-effector part id.

    Returns
    -------
    list of (float, bool)
        ``(samples, recovered)`` per change.
    """
    bounds = list(change_steps) + [n_steps]
    result = []
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        hit = next((e for e in events if e.kind in _ADAPTED and start <= e.step < stop
                    and effector in (e.parent, e.child)), None)
        result.append((float(hit.step - start + 1), True) if hit else (float(stop - start), False))
    return result


def run_protocol(protocol, seed, perception="noise"):
    """One run of one protocol; returns ``{figure key: value}`` plus ``"curves"`` and ``"events"``."""
    session = _session(protocol, seed, perception)
    tree = powercube_6dof()
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, _config(perception),
                                initial_models=engineered_models(tree), action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    effector = max(tree.marker_ids)
    column = list(session.marker_ids).index(effector)
    parts = [list(session.marker_ids).index(p) for p in tree.marker_ids if p != tree.root_marker]
    n = session.actions.shape[0]
    errors = np.full(n, np.nan)
    all_errors = np.full(n, np.nan)
    invalid = np.zeros(n, dtype=bool)
    events = []
    for t in range(n):
        predicted = learner.predict(session.actions[t])  # before the update: an unseen sample
        errors[t] = np.linalg.norm(predicted[effector][:3, 3] - session.true_poses[t, column, :3, 3])
        all_errors[t] = np.mean([np.linalg.norm(predicted[session.marker_ids[k]][:3, 3]
                                                - session.true_poses[t, k, :3, 3]) for k in parts])
        events += learner.update(session.actions[t], session.observations[t], stamp=t)
        invalid[t] = any(not s["valid"] or s["in_mismatch"] for s in learner.edge_status())
    changes = [int(step) for step, _ in session.faults]
    recovery = recovery_times(events, changes, n, effector)
    prefix = PROTOCOLS[protocol]
    (failure, ok1), (repair, ok2), (same, ok3) = recovery
    after_start = changes[0] + int(failure)
    bounds = changes + [n]
    figures = {
        f"{prefix}_recovery_failure": failure,
        f"{prefix}_recovery_repair": repair,
        f"{prefix}_recovery_same": same,
        **{f"{prefix}_invalid_{name}": float(invalid[start:stop].sum())
           for name, start, stop in zip(("failure", "repair", "same"), bounds[:-1], bounds[1:], strict=True)},
        f"{prefix}_ee_err_mm_after": 1e3 * float(np.nanmean(errors[after_start:changes[1]])),
        f"{prefix}_ee_err_mm_before": 1e3 * float(np.nanmean(errors[:changes[0]])),
        f"{prefix}_all_err_mm_after": 1e3 * float(np.nanmean(all_errors[after_start:changes[1]])),
        f"{prefix}_not_recovered": float(3 - sum((ok1, ok2, ok3))),
    }
    seen = np.mean([len(obs) / len(session.marker_ids) for obs in session.observations])
    figures["curves"] = {f"{prefix}_ee_err_mm": (1e3 * errors).tolist(), f"{prefix}_changes": changes,
                         f"{prefix}_visibility": float(seen)}
    figures["events"] = [f"{e.step} {e.kind} {e.model}" for e in events if e.kind != "input_rejected"]
    return figures


def run(seed, perception="noise", quick=False):
    """Both protocols of Table I for one seed (``quick`` changes nothing: a run takes about a second in noise mode)."""
    result = {"curves": {}, "events": {}}
    for protocol in PROTOCOLS:
        one = run_protocol(protocol, seed, perception)
        result["curves"].update(one.pop("curves"))
        result["events"][protocol] = one.pop("events")
        result.update(one)
    return result


def plot(runs, path_prefix):
    """Fig. 6: mean +- std end-effector prediction error over time for each protocol; returns the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for protocol, prefix in PROTOCOLS.items():
        curves = np.array([r["curves"][f"{prefix}_ee_err_mm"] for r in runs], dtype=float)
        mean, std = np.nanmean(curves, axis=0), np.nanstd(curves, axis=0)
        steps = np.arange(mean.size)
        fig, ax = plt.subplots(figsize=(8, 3.6))
        ax.fill_between(steps, mean - std, mean + std, alpha=0.25, label="+- std over runs")
        ax.plot(steps, mean, lw=1.2, label=f"mean over {len(runs)} runs")
        for change in runs[0]["curves"][f"{prefix}_changes"]:
            ax.axvline(change, color="k", ls=":", lw=0.8)
        ax.set(xlabel="sample", ylabel="end-effector prediction error (mm)", ylim=(0, max(60.0, 1.1 * np.nanmax(mean))),
               title=f"{protocol.replace('_', ' ')}: change at 100 and 300, repair at 200 (cf. paper Fig. 6)")
        ax.legend(loc="upper right")
        fig.tight_layout()
        path = path_prefix.parent / f"{path_prefix.name}_{prefix}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths

#: Loose bounds for ``make experiments-quick`` (a broken pipeline, not a weak result, falls outside).
SANITY = {**{f"{p}_recovery_{k}": (1.0, 100.0) for p in PROTOCOLS.values() for k in ("failure", "repair", "same")},
          **{f"{p}_invalid_{k}": (0.0, 100.0) for p in PROTOCOLS.values() for k in ("failure", "repair", "same")},
          **{f"{p}_ee_err_mm_{k}": (0.0, 500.0) for p in PROTOCOLS.values() for k in ("after", "before")},
          **{f"{p}_all_err_mm_after": (0.0, 500.0) for p in PROTOCOLS.values()}}
