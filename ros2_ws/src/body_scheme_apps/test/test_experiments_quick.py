"""The quick run of every experiment without a test file of its own, one noise level (or body, robot) per test: its
figures are finite and within the experiment's sanity bounds (what ``make experiments-quick --check`` asks of them)."""

import pytest

from body_scheme_apps.experiments.runner import aggregate, experiment_module, sanity_problems

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)

#: The experiments whose quick runs no other test file makes (fig7, table1, control, branching, transmission and zoo
#: have theirs; realdata needs the real datasets, which the project may not ship).
COVERED_HERE = ("explore", "iksure", "sparse", "yourrobot")
CASES = [(name, level) for name in COVERED_HERE for level in experiment_module(name).NOISE_LEVELS]


@pytest.mark.parametrize(("name", "level"), CASES, ids=[f"{n}-{v}" for n, v in CASES])
def test_a_quick_run_gives_sane_figures(name, level):
    module = experiment_module(name)
    run = module.run(0, level, quick=True)
    figures = getattr(module, "summarize", aggregate)([run])
    assert figures and not sanity_problems(figures, getattr(module, "SANITY", {})), figures
