"""The paper's experiments (Sec. IV), reproduced: ``python -m body_scheme_apps.experiments`` (``make experiments``).

One module per experiment, each with ``run(seed, perception, quick) -> dict`` (one run's figures and curves),
``FIGURES`` (definitions), ``PAPER`` (the paper's values), ``TARGETS`` and ``plot(runs, path_prefix)``:

- :mod:`.fig7`: Fig. 7, the 2-DOF arm learning from scratch (prediction and control error vs samples).
- :mod:`.table1`: Table I and Fig. 6, the 6-DOF arm's recovery after a blocked joint and a deformed limb.
- :mod:`.control`: Sec. IV-D, the 4-DOF arm following a trajectory by IK with a deformed middle limb.
- :mod:`.branching`: not in the paper: a branching body learned from scratch (true tree found, no false alarm).
- :mod:`.transmission`: not in the paper: a nonlinear gear learned from scratch (GP edge, its hyperparameters).
- :mod:`.zoo`: not in the paper: random bodies at five noise levels (one with 30 % flips), learned and changed once.
- :mod:`.yourrobot`: not in the paper: real arms' URDFs, markers planned, learned from rendered images, calibrated.
- :mod:`.iksure`: not in the paper: IK's reported uncertainty against where the true arm goes.
- :mod:`.explore`: the paper's future work: active exploration against random babbling.
- :mod:`.sparse`: not in the paper: real arms observed at the tool only, a chain through the unmarked links.
- :mod:`.realdata`: not in the paper: two public datasets of real arms observed at the tool (when present).

A module may set ``RUNS`` (noise-model runs of a full run, instead of ``--runs``), ``QUICK_RUNS`` (a quick run's,
if fewer than ``--runs``; default ``RUNS``), ``PERCEPTIONS`` (default both ``"noise"`` and ``"rendered"``),
``NOISE_LEVELS`` (the noise-model runs of one seed, each passed as
``perception``; default ``("noise",)``), ``summarize(runs)`` (its figures from its runs; default: the mean and std of
every scalar), ``MIN_TARGETS`` (figures where higher is better) and ``NOTES`` (text under its table).

:mod:`.runner` runs them in parallel over seeds and :mod:`.report` writes ``docs/results/`` and ``docs/RESULTS.md``.
"""
