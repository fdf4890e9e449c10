"""Bootstrapping throughput and memory on bodies from one arm to a humanoid upper body, lazy and eager side by side.

Each body bootstraps from scratch at the paper's noise (44 mm / 15 deg, every marker visible) in a fresh process
(``spawn``, one BLAS thread), once lazily (:data:`LAZY`: lazy layers and racing, ``config.lazy_layers``,
``config.race_samples``) and once eagerly (the defaults: every candidate up to ``max_complexity`` from the start, no
racing):

``bootstrap_<body>_updates_per_s`` / ``bootstrap_<body>_eager_updates_per_s``
    Update calls per second over the whole bootstrapping phase (first step to ``bootstrap_finished``).
``bootstrap_<body>_max_update_ms`` (and ``_eager_``)
    The slowest update of the phase.
``bootstrap_<body>_peak_mb`` (and ``_eager_``)
    The process's peak RSS during the phase (Linux's high-water mark ``VmHWM``, reset when the learner is built, so
    the peaks inside an update count) over its RSS then (after the imports and the session): the learner's memory.
    Where the mark cannot be reset, the largest RSS after an update (which misses the peaks inside one, and moves
    with what the allocator keeps: 69 against 96 MB on the dual arm).
``bootstrap_<body>_candidates_max`` (and ``_eager_``)
    The most candidates learning at once; ``_raced`` the candidates racing dropped; ``_steps`` the phase's length;
    ``_true_tree`` whether the tree is a true body scheme of the body (:func:`~body_scheme_core.world.is_true_tree`).

Bodies: ``paper6`` the paper's 6-DOF arm (7 markers), ``arm7`` a 7-joint arm (8 markers), ``dualarm`` a torso and
two 7-joint arms (15 markers), ``upper18`` a humanoid upper body with torso 2, head 2 and two 7-joint arms (18
joints, 20 markers; the head's marker needs both head joints: complexity 2).
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import time

from body_scheme_core.threads import limit_math_threads

from .entry import command

__all__ = ["BODIES", "LAZY", "TARGETS", "bootstrap_body", "run", "compare_trees", "main"]

#: Body name -> (constructor name in body_scheme_core.world, keyword arguments).
BODIES = {
    "paper6": ("powercube_6dof", {}),
    "arm7": ("arm_7dof", {}),
    "dualarm": ("upper_body", {}),
    "upper18": ("upper_body", {"torso_joints": 2, "head_joints": 2}),
}
#: The lazy configuration measured against the eager defaults (``lazy_layers`` and racing are off by default).
LAZY = {"lazy_layers": True, "race_samples": 3}
#: Targets of issue 21 (one core), printed next to the figures.
TARGETS = {"bootstrap_paper6_updates_per_s": (">=", 200.0), "bootstrap_arm7_updates_per_s": (">=", 200.0),
           "bootstrap_dualarm_updates_per_s": (">=", 30.0), "bootstrap_dualarm_max_update_ms": ("<=", 200.0),
           "bootstrap_upper18_updates_per_s": (">=", 15.0), "bootstrap_dualarm_peak_mb": ("<=", 150.0),
           "bootstrap_upper18_peak_mb": ("<=", 250.0)}


def _rss_mb():
    """This process's resident memory now (Linux), MB."""
    with open("/proc/self/statm", encoding="ascii") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def _reset_peak_rss():
    """Set this process's peak RSS (``VmHWM``) to its RSS now (Linux's ``clear_refs``); False where it cannot."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_mb():
    """This process's peak RSS since the last :func:`_reset_peak_rss` (``VmHWM``), MB; None where not reported."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return None


def bootstrap_body(name, eager, seed=0, max_steps=600):
    """Bootstrap body ``name`` once in this process; returns its figures (keys without the ``bootstrap_<body>_``
    prefix). Meant to run in a fresh process, so that the peak RSS is this learner's."""
    limit_math_threads(1)
    from body_scheme_core import world
    from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner

    constructor, kwargs = BODIES[name]
    body = getattr(world, constructor)(**kwargs)
    session = world.make_session(body, max_steps, seed=seed, visibility=1.0)
    config = BodySchemeConfig() if eager else BodySchemeConfig(**LAZY)
    base, marked = _rss_mb(), _reset_peak_rss()
    learner = BodySchemeLearner(body.marker_ids, body.n_actions, config, action_lower=body.action_lower,
                                action_upper=body.action_upper)
    worst, most, step, peak = 0.0, learner.n_candidates, 0, _rss_mb()
    start = time.perf_counter()
    while learner.phase == "bootstrapping" and step < max_steps:
        t = time.perf_counter()
        learner.update(session.actions[step], session.observations[step])
        worst = max(worst, time.perf_counter() - t)
        most = max(most, learner.n_candidates)
        peak = max(peak, _rss_mb())
        step += 1
    seconds = time.perf_counter() - start
    high_water = _peak_rss_mb() if marked else None
    if high_water is not None:
        peak = max(peak, high_water)
    return {"updates_per_s": step / seconds, "max_update_ms": 1000.0 * worst, "peak_mb": peak - base,
            "candidates_max": int(most), "raced": int(learner.n_raced), "steps": step,
            "finished": learner.phase != "bootstrapping",
            "true_tree": bool(world.is_true_tree(body, learner.body_scheme))}


def run(bodies=tuple(BODIES), seed=0):
    """Every body lazy and eager, each in a fresh process; the flat result dict."""
    result = {}
    context = multiprocessing.get_context("spawn")
    for name in bodies:
        for eager in (False, True):
            with context.Pool(1) as pool:
                figures = pool.apply(bootstrap_body, (name, eager, seed))
            infix = "eager_" if eager else ""
            result.update({f"bootstrap_{name}_{infix}{key}": value for key, value in figures.items()})
    return result


def table(result, bodies=tuple(BODIES)):
    """The figures as a text table, lazy next to eager, with the targets."""
    lines = [f"{'bootstrapping (paper noise)':28s} {'lazy':>10s} {'eager':>10s}  target", "-" * 62]
    for name in bodies:
        for key in ("updates_per_s", "max_update_ms", "peak_mb", "candidates_max", "raced", "steps", "true_tree"):
            lazy, eager = result[f"bootstrap_{name}_{key}"], result[f"bootstrap_{name}_eager_{key}"]
            target = TARGETS.get(f"bootstrap_{name}_{key}")
            lines.append(f"{name + ' ' + key:28s} {_cell(lazy):>10s} {_cell(eager):>10s}  "
                         f"{'' if target is None else ' '.join(map(str, target))}")
    return "\n".join(lines)


def _cell(value):
    return f"{value:.1f}" if isinstance(value, float) else str(value)


def compare_trees(n_zoo=20, n_random=6, n_branching=4, flip_rate=0.02, n_steps=300):
    """Lazy (:data:`LAZY`) against eager bootstrapping (the defaults) on bodies nobody tuned them on: robot-zoo
    bodies, random branching trees of 6 joints, branching bodies with a second torso marker and a dummy action, with
    camera-like flips. Returns ``{"bodies", "same_tree", "lazy_true", "eager_true", "differences"}``."""
    from body_scheme_core import world
    from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner

    def learn(body, config, seed):
        session = world.make_session(body, n_steps, seed=seed, flip_rate=flip_rate)
        learner = BodySchemeLearner(body.marker_ids, body.n_actions, config, action_lower=body.action_lower,
                                    action_upper=body.action_upper)
        for t in range(n_steps):
            learner.update(session.actions[t], session.observations[t])
            if learner.phase != "bootstrapping":
                break
        scheme = learner.body_scheme
        edges = None if scheme is None else sorted((m.parent, m.child, m.kind, m.actions) for m in scheme.models)
        return edges, bool(world.is_true_tree(body, scheme))

    cases = ([(f"zoo{s}", world.zoo_robot(s), s) for s in range(n_zoo)]
             + [(f"random{s}", world.random_tree(6, s, branching=True), s) for s in range(n_random)]
             + [(f"branching{s}", world.branching_tree(s, second_torso_marker=True, dummy_action=True), s)
                for s in range(n_branching)])
    out = {"bodies": len(cases), "same_tree": 0, "lazy_true": 0, "eager_true": 0, "differences": []}
    for name, body, seed in cases:
        lazy = learn(body, BodySchemeConfig(**LAZY), seed)
        eager = learn(body, BodySchemeConfig(), seed)
        out["same_tree"] += lazy[0] == eager[0]
        out["lazy_true"] += lazy[1]
        out["eager_true"] += eager[1]
        if lazy[0] != eager[0]:
            out["differences"].append({"body": name, "lazy_true": lazy[1], "eager_true": eager[1]})
    return out


@command
def main(argv=None):
    """``python -m body_scheme_apps.bootstrap_bench [--bodies paper6,dualarm] [--compare]``: print the figures."""
    parser = argparse.ArgumentParser(prog="bootstrap_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--bodies", default=",".join(BODIES), help="comma-separated (default: all)")
    parser.add_argument("--compare", action="store_true",
                        help="instead: lazy against eager trees on 30 bodies nobody tuned them on")
    args = parser.parse_args(argv)
    if args.compare:
        print(compare_trees())
        return 0
    bodies = tuple(args.bodies.split(","))
    print(table(run(bodies), bodies))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
