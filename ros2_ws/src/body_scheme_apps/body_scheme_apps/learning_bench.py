"""``body-scheme-bench``: throughput of the learner and of IK on the paper's 6-DOF arm, on one core.

Workloads (all on :func:`~body_scheme_core.world.powercube_6dof`: 7 markers, 6 actions, ``max_complexity`` 2,
i.e. 714 candidate local models (21 pairs x 1 static, 6 x (prismatic, revolute, GP), 15 two-action GPs), at the
paper's noise and with every marker visible so that every candidate is evaluated in every step):

``bootstrap_updates_per_s``
    :meth:`BodySchemeLearner.update` calls per second from the first step until ``bootstrap_finished``: per step,
    every candidate predicts the new observation of its pair, records the error and (until frozen) learns it,
    the structure search runs, and the tree is jointly fitted when it changed or its data grew.
``steady_updates_per_s``, ``steady_ms_median``, ``steady_ms_max``
    Update calls per second afterwards (tree models and memory against chain-consistent targets, the joint fit
    every ``calibration_period`` steps), over clean babbling, and the time of one update (median, max).
``joint_fit_ms``
    One joint fit of the 6-DOF tree (root pose and six revolute joints) on a full history window (200 steps,
    1400 observations), as ``BodySchemeLearner.recalibrate`` runs it (with the noise it teaches and the parts it
    checks): median of 5, each on a copy of the learner.
``sklearn_bootstrap_updates_per_s``
    The per-step GP work of the paper's learner (462 GP candidates) done with scikit-learn: for every candidate,
    ``GaussianProcessRegressor`` with the same kernel and noise (``optimizer=None``) is fitted on that candidate's
    training data and predicts the new sample. Timed at a few training-set sizes spread over the bootstrap phase;
    the rate is one over the mean step time. It leaves out everything else a learner step does (and the rigid
    candidates), so the speed-up is conservative.
``ik_ms_median``, ``ik_success_rate``
    :func:`~body_scheme_core.control.ik.solve_ik` on the learned scheme for random reachable end-effector targets (the
    scheme's own prediction at random actions), from random starts.
``parametrisation``
    Accuracy of the paper's GP parametrisation (12 independent components of ``[R | t]``, then the SVD projection
    onto SE(3): :class:`~body_scheme_core.models.gp.GPModel`) against a 6-output tangent-space GP (rotation vector
    relative to the training mean rotation, plus translation) with the same kernel and noise ratio, on random
    one-joint relations observed with the default noise, 30 training samples, for joint ranges of +-1 rad and +-pi.

BLAS threads are pinned to 1 (environment variables set before numpy is imported, and threadpoolctl when
available), so the numbers are single-core numbers.
"""

from __future__ import annotations

import os

# Before numpy is imported (this module imports nothing heavy above this line): one BLAS thread.
for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from body_scheme_apps import bootstrap_bench  # noqa: E402
from body_scheme_apps.bench_output import report  # noqa: E402
from body_scheme_core import __version__  # noqa: E402
from body_scheme_core.control import solve_ik  # noqa: E402
from body_scheme_core.learning import (  # noqa: E402
    BodySchemeConfig,
    BodySchemeLearner,
    enumerate_candidates,
)
from body_scheme_core.models import (  # noqa: E402
    GPHyperparameters,
    GPModel,
    squared_exponential,
)
from body_scheme_core.rotations import project_to_rotation  # noqa: E402
from body_scheme_core.transforms import (  # noqa: E402
    concat,
    relative_transform,
    rotational_error,
    transform_from_rotvec,
    translational_error,
    vector12_from_transform,
)
from body_scheme_core.world import make_session, powercube_6dof  # noqa: E402

from .entry import command  # noqa: E402

__all__ = ["main", "run_benchmarks"]

#: Targets from the project brief, printed next to the measurements.
TARGETS = {"bootstrap_updates_per_s": 100.0, "steady_updates_per_s": 1000.0, "speedup_vs_sklearn": 20.0,
           "ik_ms_median": 5.0, "steady_ms_median": 5.0}


def _blas_limit():
    """Context manager limiting BLAS/OpenMP pools to one thread (threadpoolctl), and a note saying how."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext(), "environment variables (threadpoolctl not installed)"
    return threadpool_limits(limits=1), "threadpoolctl + environment variables"


def _commit():
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=os.path.dirname(os.path.abspath(__file__)))
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None


def _bootstrap(session, config):
    """Run a fresh learner until bootstrapping ends; returns (learner, steps, seconds)."""
    tree = session.tree
    learner = BodySchemeLearner(tree.marker_ids, tree.n_actions, config, action_lower=tree.action_lower,
                                action_upper=tree.action_upper)
    start = time.perf_counter()
    step = 0
    while learner.phase == "bootstrapping":
        if step >= session.n_steps:
            raise RuntimeError(f"bootstrapping did not finish within {session.n_steps} steps")
        learner.update(session.actions[step], session.observations[step])
        step += 1
    return learner, step, time.perf_counter() - start


def _sklearn_step_seconds(session, config, n_train):
    """Seconds for one bootstrap step's GP work with scikit-learn at training-set size ``n_train``."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF

    tree = session.tree
    hp = GPHyperparameters.from_config(config)
    ratios, group = hp.ratios, hp.output_group
    # The GP candidates of the paper's learner (the rigid candidates have no scikit-learn counterpart).
    candidates = [(i, j, acts) for i, j, acts, _ in
                  enumerate_candidates(tree.marker_ids, tree.n_actions, config.max_complexity, ("gp",))]
    A = session.actions[: n_train + 1]
    obs = session.observations[: n_train + 1]
    targets = {}
    for i, j, _ in candidates:
        if (i, j) not in targets:
            Z = relative_transform(np.stack([o[i] for o in obs]), np.stack([o[j] for o in obs]))
            targets[(i, j)] = vector12_from_transform(Z)
    start = time.perf_counter()
    for i, j, acts in candidates:
        # A model without actions gets one constant input: the RBF kernel is then the constant kernel.
        X = A[:, list(acts)] if acts else np.zeros((n_train + 1, 1))
        Y = targets[(i, j)]
        y_mean = Y[:n_train].mean(axis=0)
        for g, ratio in enumerate(ratios):
            cols = group == g
            gp = GaussianProcessRegressor(kernel=RBF(hp.length_scale, "fixed"), alpha=ratio**2, optimizer=None)
            gp.fit(X[:n_train], Y[:n_train, cols] - y_mean[cols])
            gp.predict(X[n_train:])
    return time.perf_counter() - start


def _ik(learner, session, n_targets, seed):
    """IK timings (ms) and successes for random reachable targets of the end effector."""
    scheme = learner.body_scheme
    tree = session.tree
    part = tree.marker_ids[-1]
    lower, upper = tree.action_lower, tree.action_upper
    rng = np.random.default_rng(seed)
    times, success = [], []
    for _ in range(n_targets):
        target = scheme.predict(rng.uniform(lower, upper))[part][:3, 3]
        a0 = rng.uniform(lower, upper)
        start = time.perf_counter()
        result = solve_ik(scheme, part, target, a0, lower, upper, rng=rng, confidence=0.0)  # the model's own answer
        times.append(1000.0 * (time.perf_counter() - start))
        success.append(bool(result.success))
    return np.asarray(times), np.asarray(success)


def _tangent_gp_predict(A_train, Z_train, A_test, hyper):
    """The alternative parametrisation: GP on [rotvec(R_ref^T R), t] around the chordal-mean rotation R_ref."""
    from scipy.spatial.transform import Rotation

    R_ref = project_to_rotation(Z_train[:, :3, :3].mean(axis=0))
    Y = np.concatenate([Rotation.from_matrix(R_ref.T @ Z_train[:, :3, :3]).as_rotvec(), Z_train[:, :3, 3]], axis=1)
    mean = Y.mean(axis=0)
    ratio = float(hyper.ratios.max())
    K = squared_exponential(A_train, A_train, hyper.length_scale) + ratio**2 * np.eye(len(A_train))
    k_star = squared_exponential(A_test, A_train, hyper.length_scale)
    pred = mean + k_star @ np.linalg.solve(K, Y - mean)
    Z = transform_from_rotvec(pred[:, :3], pred[:, 3:])
    Z[:, :3, :3] = R_ref @ Z[:, :3, :3]
    return Z


def _parametrisation_comparison(seed, n_trials, n_train=30, n_test=200):
    """Mean prediction error (mm, deg) against ground truth of both parametrisations, per joint range."""
    config = BodySchemeConfig()
    hyper = GPHyperparameters.from_config(config)
    rng = np.random.default_rng(seed)
    s_t, s_r = config.prior_sigma_trans / np.sqrt(3.0), config.prior_sigma_rot / np.sqrt(3.0)
    out = {}
    for label, limit in (("range_1rad", 1.0), ("range_pi", np.pi)):
        errors = {"matrix12": [], "tangent6": []}
        for _ in range(n_trials):
            # Z(a) = A @ Rot(axis, a) @ B: one revolute joint between two markers about 0.3 m apart.
            A = transform_from_rotvec(rng.normal(size=3), rng.normal(scale=0.2, size=3))
            B = transform_from_rotvec(rng.normal(size=3), rng.normal(scale=0.2, size=3))
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)

            def relation(a, A=A, B=B, axis=axis):
                return concat(concat(A, transform_from_rotvec(np.outer(a, axis), np.zeros(3))), B)

            a_train = rng.uniform(-limit, limit, n_train)
            noise_i = transform_from_rotvec(rng.normal(scale=s_r, size=(n_train, 3)),
                                            rng.normal(scale=s_t, size=(n_train, 3)))
            noise_j = transform_from_rotvec(rng.normal(scale=s_r, size=(n_train, 3)),
                                            rng.normal(scale=s_t, size=(n_train, 3)))
            Z_train = concat(concat(relative_transform(noise_i, np.eye(4)), relation(a_train)), noise_j)
            a_test = rng.uniform(-limit, limit, n_test)
            Z_true = relation(a_test)
            gp = GPModel.from_config(0, 1, (0,), config).fit(a_train[:, None], Z_train)
            for name, Z_pred in (("matrix12", gp.predict(a_test[:, None])),
                                 ("tangent6", _tangent_gp_predict(a_train[:, None], Z_train, a_test[:, None], hyper))):
                errors[name].append((translational_error(Z_pred, Z_true).mean() * 1e3,
                                     np.degrees(rotational_error(Z_pred, Z_true)).mean()))
        for name, values in errors.items():
            values = np.asarray(values)
            out[f"{name}_{label}_trans_mm"] = float(values[:, 0].mean())
            out[f"{name}_{label}_rot_deg"] = float(values[:, 1].mean())
    out["trials"] = int(n_trials)
    out["n_train"] = int(n_train)
    return out


def run_benchmarks(quick=False, seed=0, repeats=3):
    """Run every workload; returns the result dict (also what ``main`` writes as JSON)."""
    config = BodySchemeConfig()
    robot = powercube_6dof()
    n_steady = 500 if quick else 2000
    session = make_session(robot, 200 + n_steady, seed=seed, visibility=1.0, above_ground=True)
    context, how = _blas_limit()
    with context:
        runs = [_bootstrap(session, config) for _ in range(1 if quick else repeats)]
        rates = [steps / seconds for _, steps, seconds in runs]
        learner, n_boot, _ = runs[int(np.argsort(rates)[len(rates) // 2])]
        n_candidates = len(enumerate_candidates(robot.marker_ids, robot.n_actions, config.max_complexity,
                                                config.candidate_kinds))
        step_seconds = []
        for t in range(n_boot, n_boot + n_steady):
            start = time.perf_counter()
            learner.update(session.actions[t], session.observations[t])
            step_seconds.append(time.perf_counter() - start)
        steady = n_steady / float(np.sum(step_seconds))
        fit_ms = []
        for _ in range(5):  # on copies: the learner goes on to IK as it was
            copy = BodySchemeLearner.from_state(learner.to_state())
            start = time.perf_counter()
            copy.recalibrate()
            fit_ms.append(1000.0 * (time.perf_counter() - start))
        sizes = np.linspace(1, config.train_window - 1, 3 if quick else 5).round().astype(int)
        sk_seconds = [_sklearn_step_seconds(session, config, int(n)) for n in sizes]
        sk_rate = 1.0 / float(np.mean(sk_seconds))
        ik_ms, ik_ok = _ik(learner, session, 30 if quick else 100, seed)
    parametrisation = _parametrisation_comparison(seed, 20 if quick else 100)
    bodies = bootstrap_bench.run(("paper6", "arm7") if quick else tuple(bootstrap_bench.BODIES), seed)
    bootstrap = float(np.median(rates))
    import scipy
    import sklearn

    return {
        "bootstrap_updates_per_s": bootstrap,
        "bootstrap_steps": int(n_boot),
        "steady_updates_per_s": float(steady),
        "steady_ms_median": 1000.0 * float(np.median(step_seconds)),
        "steady_ms_max": 1000.0 * float(np.max(step_seconds)),
        "steady_steps": int(n_steady),
        "joint_fit_ms": float(np.median(fit_ms)),
        "sklearn_bootstrap_updates_per_s": sk_rate,
        "sklearn_training_sizes": sizes.tolist(),
        "speedup_vs_sklearn": bootstrap / sk_rate,
        "ik_ms_median": float(np.median(ik_ms)),
        "ik_ms_p90": float(np.percentile(ik_ms, 90)),
        "ik_success_rate": float(np.mean(ik_ok)),
        "ik_targets": int(ik_ok.size),
        "n_candidates": int(n_candidates),
        "parametrisation": parametrisation,
        "robot": "powercube_6dof (7 markers, 6 actions)",
        "max_complexity": config.max_complexity,
        "train_window": config.train_window,
        "scheme_exact": bool({frozenset((p, c)) for p, c, _, _ in learner.body_scheme.edges}
                             == {frozenset(e) for e in robot.marker_tree_edges()}),
        "blas_threads": 1,
        "blas_pinning": how,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "sklearn": sklearn.__version__,
        "core_version": __version__,
        "commit": _commit(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "quick": bool(quick),
        **bodies,
    }


def _table(result):
    rows = [
        (f"bootstrap updates/s ({result['n_candidates']} candidates)", "bootstrap_updates_per_s", ">= 100"),
        ("steady-state updates/s", "steady_updates_per_s", ">= 1000"),
        ("steady-state update median (ms)", "steady_ms_median", "<= 5"),
        ("steady-state update max (ms)", "steady_ms_max", ""),
        ("joint fit of the 6-DOF tree (ms)", "joint_fit_ms", ""),
        ("sklearn bootstrap updates/s", "sklearn_bootstrap_updates_per_s", ""),
        ("speed-up vs sklearn", "speedup_vs_sklearn", ">= 20"),
        ("IK median (ms)", "ik_ms_median", "<= 5"),
        ("IK success rate", "ik_success_rate", ""),
    ]
    lines = [f"{'measure':40s} {'value':>12s}  target", "-" * 62]
    for label, key, target in rows:
        value = result[key]
        lines.append(f"{label:40s} {value:12.3f}  {target}" if value < 100 else f"{label:40s} {value:12.1f}  {target}")
    p = result["parametrisation"]
    lines.append(f"GP parametrisation, mean error vs ground truth ({p['trials']} one-joint relations, "
                 f"{p['n_train']} noisy samples):")
    for label, text in (("range_1rad", "joint range +-1 rad"), ("range_pi", "joint range +-pi")):
        lines.append(f"  {text:18s} 12 components + SVD: {p[f'matrix12_{label}_trans_mm']:6.1f} mm "
                     f"{p[f'matrix12_{label}_rot_deg']:5.2f} deg   tangent space (6): "
                     f"{p[f'tangent6_{label}_trans_mm']:6.1f} mm {p[f'tangent6_{label}_rot_deg']:5.2f} deg")
    lines.append(f"(python {result['python']}, numpy {result['numpy']}, BLAS threads pinned to 1 via "
                 f"{result['blas_pinning']}; structure recovered exactly: {result['scheme_exact']})")
    bodies = [name for name in bootstrap_bench.BODIES if f"bootstrap_{name}_updates_per_s" in result]
    lines.append(bootstrap_bench.table(result, bodies))
    return "\n".join(lines)


@command
def main(argv=None):
    """Console entry point: run the benchmarks, print a table, write the JSON file."""
    parser = argparse.ArgumentParser(prog="body-scheme-bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join("out", "bench", "core.json"),
                        help="JSON file to write (directories are created; default: %(default)s)")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions and targets (a smoke run)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic session (default: 0)")
    parser.add_argument("--copy", default=None, help="also write the JSON here (make bench: docs/results/bench.json)")
    args = parser.parse_args(argv)
    result = run_benchmarks(quick=args.quick, seed=args.seed)
    if args.copy:
        report(result, "", args.copy)
    return report(result, _table(result), args.out)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
