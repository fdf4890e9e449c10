"""``python -m body_scheme_apps.experiments``: run the paper's experiments and write plots, results.json, RESULTS.md.

``make experiments``: 20 noise-model runs and 1 rendered-camera run per experiment into ``docs/results/`` and
``docs/RESULTS.md``. ``make experiments-quick``: 1 quick noise run (per noise level) and 1 quick rendered run into
``out/experiments-quick/``, then checks that every figure is finite and within loose sanity bounds (exit 1 if not);
CI runs the same quick runs as tests (each experiment's test file, ``test_experiments_quick.py``).
``--only NAME --keep`` reruns one experiment and keeps the others' figures and plots from the ``results.json`` in
``--out`` (the header then sums both runs' seconds and names the commit of this one).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import subprocess
import sys
import time

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one BLAS thread per process
    os.environ.setdefault(_name, "1")

from ..entry import command  # noqa: E402
from .report import write_results_json, write_results_md  # noqa: E402
from .runner import EXPERIMENTS, Task, aggregate, experiment_module, run_tasks, sanity_problems  # noqa: E402


def _commit():
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, check=True).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _kept(out, rerun):
    """Figures, rendered figures, plots and meta of the experiments not in ``rerun`` from ``out/results.json``."""
    old = json.loads((out / "results.json").read_text())  # there: checked before the runs
    names = [name for name in EXPERIMENTS if name not in rerun]
    figures = {key for name in names for key in experiment_module(name).FIGURES}
    noise = {k: v for k, v in old.items() if k in figures or (k.endswith("_std") and k[:-4] in figures)}
    rendered = {k: v for k, v in old.get("rendered", {}).items() if k in figures}
    plots = {name: sorted(out.glob(f"{name}*.png")) for name in names}
    return noise, rendered, plots, old


@command
def main(argv=None):
    """Console entry point."""
    parser = argparse.ArgumentParser(prog="python -m body_scheme_apps.experiments", description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=20,
                        help="noise-model runs per experiment (seeds seed..); an experiment may ask for another "
                             "number (RUNS; with --quick QUICK_RUNS or RUNS, if fewer than --runs)")
    parser.add_argument("--rendered-runs", type=int, default=1, help="rendered-camera runs per experiment")
    parser.add_argument("--quick", action="store_true", help="the experiments' small CI versions")
    parser.add_argument("--only", nargs="+", choices=EXPERIMENTS, default=list(EXPERIMENTS))
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: cores)")
    parser.add_argument("--out", default="docs/results", help="directory for results.json and the plots")
    parser.add_argument("--md", default=None,
                        help="the RESULTS.md to write ('' for none; default: docs/RESULTS.md with the default --out, "
                             "else RESULTS.md in --out)")
    parser.add_argument("--check", action="store_true", help="exit 1 unless all figures are finite and sane")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--keep", action="store_true",
                        help="keep the figures of the experiments not in --only from the results.json in --out")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.rendered_runs < 0:
        parser.error("--runs must be >= 1 and --rendered-runs >= 0")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.md is None:  # a run into another directory never overwrites the committed report
        args.md = "docs/RESULTS.md" if out == pathlib.Path("docs/results") else str(out / "RESULTS.md")
    if args.keep and not (out / "results.json").is_file():
        raise SystemExit(f"--keep needs an earlier {out / 'results.json'}")  # before minutes of runs, not after
    experiments = {name: experiment_module(name) for name in args.only}
    run_counts = {name: getattr(module, "RUNS", args.runs) for name, module in experiments.items()}
    if args.quick:
        run_counts = {name: min(args.runs, getattr(module, "QUICK_RUNS", run_counts[name]))
                      for name, module in experiments.items()}
    rendered_runs = {name: args.rendered_runs if "rendered" in getattr(module, "PERCEPTIONS", ("noise", "rendered"))
                     else 0 for name, module in experiments.items()}
    tasks = [Task(name, args.seed + k, variant, args.quick) for name, module in experiments.items()
             for k in range(run_counts[name]) for variant in tuple(getattr(module, "NOISE_LEVELS", ("noise",)))]
    tasks += [Task(name, args.seed + k, "rendered", args.quick) for name in experiments
              for k in range(rendered_runs[name])]
    commit = _commit()  # of the code that runs, before this run's plots and figures make the tree dirty
    start = time.monotonic()
    outcomes = run_tasks(tasks, jobs=args.jobs, progress=not args.quiet)
    seconds = time.monotonic() - start
    failed = [o for o in outcomes if o.error]
    for outcome in failed:
        print(f"FAILED {outcome.task}: {outcome.error}", file=sys.stderr)

    noise, rendered, plots, problems, failed_plots = {}, {}, {}, [], []
    old_meta = {}
    if args.keep:
        noise, rendered, plots, old_meta = _kept(out, experiments)
    for name, module in experiments.items():
        variants = tuple(getattr(module, "NOISE_LEVELS", ("noise",)))
        runs = [o.result for o in outcomes if o.task.experiment == name and o.task.perception in variants
                and o.result]
        shown = [o.result for o in outcomes if o.task.experiment == name and o.task.perception == "rendered"
                 and o.result]
        summarize = getattr(module, "summarize", aggregate)
        if runs:
            noise.update(summarize(runs))
            try:
                plots[name] = module.plot(runs, out / name)
            except Exception as error:  # the figures of a long run are still written
                failed_plots.append(name)
                print(f"FAILED {name}'s plot: {type(error).__name__}: {error}", file=sys.stderr)
        if shown:
            rendered.update(aggregate(shown))
        bounds = getattr(module, "SANITY", {})
        problems += [f"{name} (noise): {p}" for p in sanity_problems(summarize(runs), bounds)] if runs else \
            [f"{name}: no successful noise run"]
        if rendered_runs[name]:
            problems += [f"{name} (rendered): {p}" for p in sanity_problems(aggregate(shown), bounds)] if shown \
                else [f"{name}: no successful rendered run"]
    meta = {"seed": args.seed, "commit": commit, "runs": args.runs,
            "runs_per_experiment": {**old_meta.get("runs_per_experiment", {}), **run_counts},
            "rendered_runs": args.rendered_runs,
            "quick": args.quick, "jobs": args.jobs, "seconds": round(seconds + old_meta.get("seconds", 0.0), 1),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
    write_results_json(out / "results.json", noise, rendered, meta)
    command = "make experiments-quick" if args.quick else "make experiments"
    if args.md:
        if args.keep:
            command += f"`, then `python -m body_scheme_apps.experiments --only {' '.join(experiments)} --keep"
        reported = {name: experiment_module(name) for name in EXPERIMENTS if name in experiments or name in plots}
        write_results_md(pathlib.Path(args.md), reported, noise, rendered, plots, meta, command)
    print(f"{len(outcomes) - len(failed)}/{len(outcomes)} runs in {seconds:.0f} s; wrote {out / 'results.json'}"
          + (f" and {args.md}" if args.md else ""))
    for key, value in noise.items():
        if not key.endswith("_std"):
            shown = rendered.get(key, float("nan"))
            spread = noise.get(key + "_std")
            spread = "" if spread is None else f" ± {spread:.3f}"
            print(f"  {key:40s} {value:10.3f}{spread:8s}   rendered {shown:.2f}")
    if args.check and (problems or failed):
        print("sanity check FAILED:\n  " + "\n  ".join(problems + [f"{o.task}: {o.error}" for o in failed]),
              file=sys.stderr)
        return 1
    return 1 if failed_plots else 0


if __name__ == "__main__":
    sys.exit(main())
