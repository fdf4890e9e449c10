"""The quick run of every experiment without a test file of its own, one noise level (or body, robot) per test: its
figures are finite and within the experiment's sanity bounds (what ``make experiments-quick --check`` asks of them;
CI runs this instead, so that no experiment runs twice there)."""

import pytest

from body_scheme_apps.experiments.runner import aggregate, experiment_module, sanity_problems

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)

#: The experiments whose quick runs no other test file makes (fig7, table1, control, branching, transmission and zoo
#: have theirs; realdata needs the real datasets, which the project may not ship), at their cheapest noise levels
#: (bodies, robots): the others are the same code on larger bodies, except sparse's ``fault`` (a block on a chain, 40 s
#: of CPU; the learner's chain tests block a chain too); ``make experiments-quick`` runs every level.
CASES = [("explore", "2dof"), ("explore", "arm7"), ("iksure", "paper"), ("iksure", "realcam"),
         ("sparse", "iiwa"), ("sparse", "iiwa_urdf"), ("sparse", "points"), ("sparse", "active"),
         ("yourrobot", "xarm6")]


def test_the_cases_are_levels_of_their_experiments():
    assert all(level in experiment_module(name).NOISE_LEVELS for name, level in CASES)


@pytest.mark.parametrize(("name", "level"), CASES, ids=[f"{n}-{v}" for n, v in CASES])
def test_a_quick_run_gives_sane_figures(name, level):
    module = experiment_module(name)
    run = module.run(0, level, quick=True)
    figures = getattr(module, "summarize", aggregate)([run])
    assert figures and not sanity_problems(figures, getattr(module, "SANITY", {})), figures


@pytest.mark.parametrize("seed", [13, 19])
def test_a_tool_seen_by_a_tracker_past_seven_joints_is_learned_from_scratch(seed):
    """sparse's ``points`` (three reflectors on an iiwa's tool, the tracker as root), the two seeds of 20 that once
    ended with a GP of one action for the whole arm: the generous noise prior let it pass while the identified chain's
    fit, adopted after a veto, taught the noise nothing, and a failed GP was never replaced by a chain. Now the
    chain is learned (held-out error within 2 mm)."""
    from body_scheme_apps.experiments import sparse

    assert sparse.run(seed, "points", quick=True)["sparse_points_heldout_mm"] < 2.0
