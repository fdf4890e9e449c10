"""Detection: which tree model no longer matches the observations (paper Sec. III-E).

After bootstrapping, each tree model and each remembered model that has a target records its prequential error
(:meth:`~body_scheme_core.learning.pool.ModelPool.evaluate`) against the chain-consistent targets of the calibrated
body scheme (:mod:`~body_scheme_core.learning.chain`). A tree model is in *mismatch* when a one-sided CUSUM on its
normalised per-sample error crosses ``cusum_threshold``, its test window is invalid, or a remembered model of its pair
clearly fits the samples since the CUSUM left zero better (the memory challenge). A chain-consistent error rises for
every edge below a changed one (their parent's predicted pose is wrong too), so an alarm is attributed to the edge
nearest the root on its path whose CUSUM rose with it (:func:`upstream_edges`); the edges below wait (they get no
targets while a part above them is in mismatch) and restart their detectors when it is repaired.

The steps are functions of ``adapt`` (:class:`~body_scheme_core.learning.adaptation.Adaptation`: the pool, the
configuration, the history, the edges in mismatch, the replacements refining and the pairs that failed); they
change it and the tree in place and append their events. :func:`root_most_rising` takes the pool and the alarm
level only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import networkx as nx
import numpy as np

from ..errors import ModelFileError
from ..events import Event, finite_or_none, format_errors
from ..limits import MAX_INTEGER
from ..state_values import integer, listing, mapping

__all__ = ["Mismatch", "upstream_edges", "detect", "flag", "root_most_rising", "mismatch_state",
           "mismatch_from_state"]

#: An alarm is attributed to an edge above it only if that edge's CUSUM reached this fraction of the alarm level: a
#: change above raises the errors of its own child too, while healthy edges wander a little above zero (up to 0.7 of
#: the drift-adjusted statistic on clean data, learning-and-adaptation.md Sec. 6).
_ATTRIBUTION_FRACTION = 0.5
#: The memory challenge needs the tree model's CUSUM at this fraction of the alarm level: a changed part's first sample
#: (clipped at ``cusum_clip``) raises it by ``clip - drift`` = 4.5 of 12 with the defaults.
_CHALLENGE_FRACTION = 0.25


@dataclass
class Mismatch:
    """A tree edge whose model no longer matches the observations, until it is repaired.

    Attributes
    ----------
    tau : int
        Estimated change point (step): data from here on is post-change data.
    detected : int
        Step of detection.
    sampled_at : int
        Step at which replacements were last sampled; -1 before.
    train_from : int
        First step of the replacements' training data.
    resamples : int
        How often replacements were sampled again after ``replacement_patience``.
    bridged_at : int
        Step at which candidates of other pairs across the cut were sampled; -1 before.
    search : int
        1 when the edge is searched for like a new one (:func:`flag`: the joint fit left a part below it
        unexplained; or its pair failed again within ``2 test_window`` steps): no remembered model is asked (the body
        did not change back), candidates of the pair and of every pair across the cut are sampled together, and the
        cheapest by absolute complexity wins, as while bootstrapping.
    """

    tau: int
    detected: int
    sampled_at: int = -1
    train_from: int = -1
    resamples: int = 0
    bridged_at: int = -1
    search: int = 0


#: The fields of a :class:`Mismatch` in a state file, with their bounds (-1: not yet).
_MISMATCH_FIELDS = (("tau", 0, MAX_INTEGER), ("detected", 0, MAX_INTEGER), ("sampled_at", -1, MAX_INTEGER),
                    ("train_from", -1, MAX_INTEGER), ("resamples", 0, MAX_INTEGER), ("bridged_at", -1, MAX_INTEGER),
                    ("search", 0, 1))


def upstream_edges(root, edges):
    """Per tree edge, the edges on the path from the root to its part nearer the root, root-most first.

    Parameters
    ----------
    root : int
    edges : iterable of (int, int, key)
        The tree's edges ``(part, part, key)``, in any orientation.

    Returns
    -------
    upstream : dict of key to list of key
    """
    edges = list(edges)
    graph = nx.Graph()
    graph.add_node(root)
    for u, v, key in edges:
        graph.add_edge(u, v, key=key)
    above = {root: None}  # part -> (part above it, key of the edge between them)
    depth = {root: 0}
    for u, v in nx.bfs_edges(graph, root):
        above[v] = (u, graph.edges[u, v]["key"])
        depth[v] = depth[u] + 1
    out = {}
    for u, v, key in edges:
        part = u if depth[u] < depth[v] else v
        path = []
        while above[part] is not None:
            part, edge = above[part]
            path.append(edge)
        out[key] = path[::-1]
    return out


def detect(adapt, tree, root, alarms, step, events):
    """Mismatch detection on the tree edges evaluated in this step (``alarms``: CUSUM alarm by model id; ``root``:
    the tree's root part)."""
    c = adapt.config
    pool = adapt.pool
    monitor = pool.monitor
    observed = [pool.tracked[i] for i in tree if i in alarms and i not in adapt.mismatch]
    if not observed:
        return
    upstream = None  # the tree's paths, found when an edge alarms (rarely: not every step)
    st, valid = pool.window_stats([e.row for e in observed], [pool.n_now(e) for e in observed])
    for k, e in enumerate(observed):
        if e.id in adapt.mismatch:  # attributed from an edge below it earlier in this loop
            continue
        window_bad = st.n[k] >= c.min_test_samples and not valid[k]
        if not (alarms[e.id] or window_bad):
            _challenge_from_memory(adapt, e, step, events, st, k)
            continue
        if upstream is None:
            upstream = upstream_edges(root, [(pool.tracked[i].parent, pool.tracked[i].child, i) for i in tree])
        above = upstream.get(e.id, [])
        if any(i in adapt.mismatch for i in above):
            continue  # its errors follow from the edge above (it should not have had a target)
        culprit = root_most_rising(pool, c.cusum_threshold, above, e)
        if culprit is None:
            _start_mismatch(adapt, e, step, events, bool(alarms[e.id]), st, k)
            continue
        f = pool.tracked[culprit]
        st_f, _ = pool.window_stats([f.row], [pool.n_now(f)])
        cause = (f"the errors of {e.describe()} below it rose with its own (CUSUM "
                 f"{monitor.cusum[f.row][0]:.2f} / {monitor.cusum[f.row][1]:.2f} since step "
                 f"{int(monitor.change_point([f.row])[0])})")
        _start_mismatch(adapt, f, step, events, False, st_f, 0, cause=cause)


def root_most_rising(pool, cusum_threshold, above, entry):
    """The edge nearest the root among ``above`` (model ids of ``pool``) whose CUSUM excursion started no later than
    ``entry``'s and reached at least ``_ATTRIBUTION_FRACTION`` of the alarm level ``cusum_threshold`` (a noise
    excursion of a healthy edge does not)."""
    monitor = pool.monitor
    start = int(monitor.change_point([entry.row])[0])
    start = math.inf if start < 0 else start
    level = _ATTRIBUTION_FRACTION * cusum_threshold
    for i in above:
        f = pool.tracked[i]
        if not np.any(monitor.cusum[f.row] >= level):
            continue
        tau = int(monitor.change_point([f.row])[0])
        if 0 <= tau <= start + 1:
            return i
    return None


def _challenge_from_memory(adapt, entry, step, events, st, k):
    """Start a mismatch early when a remembered model of the same pair clearly fits the recent samples better.

    Only while the tree model's CUSUM is up by :data:`_CHALLENGE_FRACTION` of the alarm level (evidence of a drift,
    which one sample of a real change gives; noise excursions stay lower): over the samples since the excursion
    started, a remembered model must be valid (at least ``reinstate_min_samples`` samples) and beat the tree model
    in a paired comparison in both channels, by more than ``challenge_margin`` on average. This is what lets a
    repair, or the same failure again, be handled within a few samples.
    """
    c = adapt.config
    monitor = adapt.pool.monitor
    if not np.any(monitor.cusum[entry.row] >= _CHALLENGE_FRACTION * c.cusum_threshold):
        return
    memory = adapt.pool.memory_of_pair(entry.parent, entry.child)
    if not memory:
        return
    tau = int(monitor.change_point([entry.row])[0])
    rows = [e.row for e in memory]
    ok = monitor.valid(monitor.stats(rows, since=tau), c.reinstate_min_samples)
    n, diff = monitor.paired_difference(rows, [entry.row] * len(rows), since=tau)
    better = (ok & (n >= c.reinstate_min_samples) & (diff.mean(axis=1) < -c.challenge_margin)
              & np.all(diff < 0.0, axis=1))
    if np.any(better):
        best = int(np.argmin(np.where(better, diff.mean(axis=1), np.inf)))
        cause = (f"remembered {memory[best].describe()} fits the {n[best]} samples since step {tau} better by "
                 f"{-diff[best, 0]:.2f} (trans) / {-diff[best, 1]:.2f} (rot) thresholds")
        _start_mismatch(adapt, entry, step, events, False, st, k, cause=cause)


def flag(adapt, entry, step, events, cause):
    """Put tree edge ``entry`` in mismatch for a reason the detectors did not see (the joint fit left a part below
    it unexplained): it is repaired like a detected change, by remembered models, replacements of other classes
    and action sets, and pairs across the cut. The change point is the CUSUM's if it rose, else the oldest step of
    the history (the model may have been wrong all along)."""
    st, _ = adapt.pool.window_stats([entry.row], [adapt.pool.n_now(entry)])
    oldest = adapt.history[0][0] if adapt.history else step
    _start_mismatch(adapt, entry, step, events, False, st, 0, cause=cause, fallback_tau=oldest, search=True)


def _start_mismatch(adapt, entry, step, events, alarm, st, k, cause=None, fallback_tau=None, search=False):
    """Put ``entry`` in mismatch, with the change point from its CUSUM (else ``fallback_tau``, else the oldest
    window sample); searched for like a new edge (``search``, or when its pair failed within ``2 test_window``
    steps: repairing it the usual way did not last)."""
    c = adapt.config
    monitor = adapt.pool.monitor
    n, mt, mr = int(st.n[k]), float(st.trans_error[k]), float(st.rot_error[k])
    theta_t, theta_r = float(st.theta_trans[k]), float(st.theta_rot[k])
    tau = int(monitor.change_point([entry.row])[0])
    if tau < 0 and fallback_tau is not None:
        tau = int(fallback_tau)
    elif tau < 0:
        tau = int(monitor.first_step([entry.row])[0])
        tau = step if tau < 0 else tau
    S = monitor.cusum[entry.row]
    if cause is None:
        cause = (f"CUSUM {S[0]:.2f} (trans) / {S[1]:.2f} (rot) reached {c.cusum_threshold:g}" if alarm
                 else f"test window invalid over {n} samples")
    pair = frozenset((entry.parent, entry.child))
    last, last_tau = adapt.failed.get(pair, (-math.inf, tau))
    again = step - last <= 2 * c.test_window
    if again:  # the repair of the same change did not last: its data since that change point is still good
        tau = min(tau, last_tau)
    adapt.failed[pair] = (step, tau)
    adapt.mismatch[entry.id] = Mismatch(tau=tau, detected=step, train_from=tau, search=int(search or again))
    events.append(Event(step, "mismatch_detected",
                        f"{entry.describe()} no longer matches the observations: {cause}; window mean "
                        f"{format_errors(mt, mr)} over {n} samples (thresholds "
                        f"{format_errors(theta_t, theta_r)}); change point estimated at step {tau}",
                        parent=entry.parent, child=entry.child, model=entry.describe(),
                        trans_error=finite_or_none(mt), rot_error=finite_or_none(mr)))


# ------------------------------------------------------------------ state
def mismatch_state(mismatch):
    """The edges in mismatch as JSON-serialisable dicts ``{"edge": id, "tau": ..., ...}``."""
    return [{"edge": k, **asdict(v)} for k, v in mismatch.items()]


def mismatch_from_state(items, tracked):
    """Rebuild ``Adaptation.mismatch`` from :func:`mismatch_state` output; edges must be ids in ``tracked``."""
    mismatch = {}
    for item in listing(items, "mismatch"):
        item = dict(mapping(item, "mismatch item"))
        edge = integer(item.pop("edge", None), "mismatch edge")
        if edge not in tracked or edge in mismatch:
            raise ModelFileError(f"mismatch refers to unknown model id {edge}, or twice")
        mismatch[edge] = Mismatch(**{k: integer(item[k], f"mismatch {k}", minimum=low, maximum=high)
                                     for k, low, high in _MISMATCH_FIELDS})
    return mismatch
