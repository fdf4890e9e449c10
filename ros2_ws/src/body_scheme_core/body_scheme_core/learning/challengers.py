"""Challengers: a GP for a rigid joint of the tree that a rigid joint cannot describe (paper Sec. III-B).

Right after bootstrapping, every rigid joint of the tree gets a GP challenger trained on the chain-consistent history;
it takes the edge only if it predicts the same samples clearly better (a nonlinear transmission, a flexing tool), else
it is dropped.

The steps are functions of ``adapt`` (:class:`~body_scheme_core.learning.adaptation.Adaptation`: the pool, the
configuration, the history, the edges in mismatch, the replacements refining and the pairs that failed); they
change it and the tree in place and append their events.
"""

from __future__ import annotations

from ..events import Event, format_errors
from .repair import Change, choose_replacement, clearly_better, dominating, replay
from .tracked import TREE

__all__ = ["sample_challengers", "challenge"]


def sample_challengers(adapt, tree, chain, chain_at, step, events):
    """Challengers of the tree's models in the other direction of flexibility, trained on the chain-consistent
    history: a GP for every rigid joint, and the rigid forms for every GP edge on one action.

    Relative observations cannot tell a rigid joint from a smooth nonlinear relation (a transmission, a flexing
    tool) at the paper's noise; chain-consistent targets can. Early in bootstrapping, a GP judged against its own
    wide uncertainty can also win an edge that a rigid joint describes with fewer parameters and less error.
    ``chain`` (this step's targets) orients each challenger from the root's side; ``chain_at`` gives the targets
    of past steps. Each challenger learns like a replacement candidate and is judged by :func:`challenge`; it is
    dropped once frozen and compared with the tree model over a full window of common samples without taking
    the edge.
    """
    pool = adapt.pool
    kinds = adapt.config.candidate_kinds
    rigid = [pool.tracked[i] for i in tree if pool.tracked[i].kind in ("static", "prismatic", "revolute")
             and pool.tracked[i].actions] if "gp" in kinds else []
    flexible = [pool.tracked[i] for i in tree if pool.tracked[i].kind == "gp"
                and len(pool.tracked[i].actions) == 1]
    simpler = [k for k in ("prismatic", "revolute") if k in kinds]
    challengers = []
    for e in rigid:
        u, v = chain.orient(e.parent, e.child)  # from the root's side, the direction of their targets
        challengers += pool.add_learning([(u, v, e.actions, "gp")], origin="challenger", created=step,
                                         target=e.id)
    for e in flexible if simpler else []:
        u, v = chain.orient(e.parent, e.child)
        challengers += pool.add_learning([(u, v, e.actions, kind) for kind in simpler], origin="challenger",
                                         created=step, target=e.id)
    if not challengers:
        return
    used = replay(pool, adapt.history, challengers, chain_at, start=-1)
    what = []
    if rigid:
        what.append(f"a GP for each of the {len(rigid)} rigid joints (a relation no rigid form explains would "
                    f"show here)")
    if flexible and simpler:
        what.append(f"{' and '.join(simpler)} joints for each of the {len(flexible)} GP edges on one action (a "
                    f"rigid joint that predicts as well takes the edge)")
    events.append(Event(step, "model_sampled",
                        f"sampled challengers of the tree's models: {'; '.join(what)} "
                        f"({', '.join(e.describe() for e in challengers)}), trained on the {used} "
                        f"chain-consistent samples of the history"))


def challenge(adapt, tree, step, events):
    """Challengers that take their tree model's edge: a GP that dominates a rigid joint, or a valid rigid joint
    that a GP edge does not predict clearly better over a full window of common samples. The others are dropped
    once they are frozen and were compared with it over a full window. Returns the changes."""
    pool = adapt.pool
    c = adapt.config
    changes = []
    for current_id in [i for i in tree]:
        challengers = [e for e in pool.candidates_of(current_id) if e.origin == "challenger"]
        if not challengers:
            continue
        current = pool.tracked[current_id]
        if current_id in adapt.mismatch:
            continue
        if current.kind == "gp":
            choice = _simpler(adapt, current, challengers)
            found = None if choice is None else (choice.entry, choice.n_test, choice.trans_error,
                                                 choice.rot_error)
            why = "a rigid joint predicts the same chain-consistent samples as well, with fewer parameters"
        else:
            found = dominating(pool, c, current, challengers)
            why = ("it predicts the same chain-consistent samples clearly better: no rigid form explains this "
                   "relation")
        if found is not None:
            new, n, mt, mr = found
            pool.freeze(new)
            pool.assign(new, TREE, step)
            new.since = current.since
            tree[tree.index(current_id)] = new.id
            pool.monitor.reset_cusum([new.row])
            for e in pool.candidates_of(current_id):
                if e is not new:
                    pool.remove(e)
            events.append(Event(step, "model_replaced",
                                f"{new.describe()} replaces {current.describe()}: {why} (mean error "
                                f"{format_errors(mt, mr)} over {n} test samples)",
                                parent=new.parent, child=new.child, model=new.describe(),
                                trans_error=mt, rot_error=mr))
            pool.remove(current)
            changes.append(Change(new, current, new.since))
            continue
        # Judged: frozen, and compared with the tree model on a full window of common samples.
        n, _ = pool.monitor.paired_difference([e.row for e in challengers], [current.row] * len(challengers),
                                              [pool.n_now(e) for e in challengers],
                                              [pool.n_now(current)] * len(challengers), c.stale_fraction)
        for e, n_common in zip(challengers, n, strict=True):
            if pool.n_now(e) >= c.train_window and n_common >= c.test_window:
                pool.remove(e)
    return changes


def _simpler(adapt, current, challengers):
    """The cheapest valid rigid challenger of a GP edge
    (:func:`~body_scheme_core.learning.repair.choose_replacement`) once it shares a full test window of samples
    with it and the GP does not predict them clearly better; else None."""
    choice = choose_replacement(adapt.pool, current, challengers, absolute=True)
    if choice is None:
        return None
    pool = adapt.pool
    n, _ = pool.monitor.paired_difference([current.row], [choice.entry.row], [pool.n_now(current)],
                                          [pool.n_now(choice.entry)], adapt.config.stale_fraction)
    if n[0] < adapt.config.test_window or clearly_better(adapt.pool, adapt.config, current, choice.entry):
        return None
    return choice
