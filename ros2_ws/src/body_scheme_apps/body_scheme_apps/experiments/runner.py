"""Run the experiments over seeds in parallel worker processes and aggregate their figures.

Each task is one ``(experiment, seed, perception)`` run of an experiment module's ``run(seed, perception, quick)``;
tasks run in a process pool (one BLAS thread per worker, so ``jobs`` workers use ``jobs`` cores) with a progress bar.
"""

from __future__ import annotations

import importlib
import math
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np

from body_scheme_core.threads import limit_math_threads

__all__ = ["EXPERIMENTS", "Task", "experiment_module", "run_tasks", "aggregate", "sanity_problems"]

#: Experiment name -> module (in this package), in the order of the paper.
EXPERIMENTS = ("fig7", "table1", "control", "branching", "transmission", "zoo", "yourrobot", "iksure",
               "explore", "sparse", "realdata")
_SKIP = ("curves", "events")


def experiment_module(name):
    """The module of an experiment (see the package docstring for its interface)."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; known: {EXPERIMENTS}")
    return importlib.import_module(f"{__package__}.{name}")


@dataclass(frozen=True)
class Task:
    """One run: ``experiment_module(experiment).run(seed, perception, quick)``."""

    experiment: str
    seed: int
    perception: str
    quick: bool = False


@dataclass
class Outcome:
    """A finished task: its result dict, or the error it raised (as text)."""

    task: Task
    result: dict = field(default_factory=dict)
    error: str | None = None


def _one_thread():
    limit_math_threads(1)  # the figures are single-core figures, whatever the user's BODY_SCHEME_MATH_THREADS


def _execute(task):
    try:
        return Outcome(task, experiment_module(task.experiment).run(task.seed, task.perception, task.quick))
    except Exception as error:  # reported with the task, the other runs go on
        return Outcome(task, error=f"{type(error).__name__}: {error}")


def run_tasks(tasks, jobs=None, progress=True):
    """Run ``tasks`` in ``jobs`` worker processes (default: all cores); returns the outcomes in task order."""
    jobs = max(1, int(jobs or os.cpu_count() or 1))
    outcomes = {}
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(tasks), unit="run", desc="experiments")
    with ProcessPoolExecutor(max_workers=jobs, initializer=_one_thread) as pool:
        futures = {pool.submit(_execute, task): k for k, task in enumerate(tasks)}
        for future in as_completed(futures):
            outcome = future.result()
            outcomes[futures[future]] = outcome
            if bar is not None:
                bar.set_postfix_str(f"{outcome.task.experiment} seed {outcome.task.seed} {outcome.task.perception}")
                bar.update(1)
    if bar is not None:
        bar.close()
    return [outcomes[k] for k in range(len(tasks))]


def aggregate(results):
    """Mean and std over runs of every scalar figure: ``{key: mean, key + "_std": std}`` (NaN-aware)."""
    keys = [k for k in results[0] if k not in _SKIP] if results else []
    summary = {}
    for key in keys:
        values = np.array([r.get(key, math.nan) for r in results], dtype=float)
        finite = values[np.isfinite(values)]
        summary[key] = float(np.mean(finite)) if finite.size else math.nan
        summary[key + "_std"] = float(np.std(finite)) if finite.size else math.nan
    return summary


def sanity_problems(summary, bounds):
    """Figures that are not finite or outside loose ``bounds`` ``{key: (low, high)}``; a list of messages."""
    problems = []
    for key, value in summary.items():
        if key.endswith("_std"):
            continue
        if not math.isfinite(value):
            problems.append(f"{key} is {value}")
        elif key in bounds and not bounds[key][0] <= value <= bounds[key][1]:
            problems.append(f"{key} = {value:.3g} outside the sanity bounds {bounds[key]}")
    return problems
