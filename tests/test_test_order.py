"""How the suite itself runs: what ``make test`` runs first, and on how many math threads."""

import subprocess
import sys

import pytest
from workspace import REPO


@pytest.mark.slow  # 2 s: a pytest collection; make test's order
def test_heavy_tests_are_collected_first_the_longest_first():
    """pytest-xdist hands tests out in collection order: the heavy ones first (conftest.py), or a 20-s test collected
    late runs alone at the end while the other worker idles. (The DDS system tests are not reordered: the rendered
    graph's story depends on timing, and with the your-robot rehearsal beside it a CI run lost its tree.)"""
    files = ["ros2_ws/src/body_scheme_core/test/learning/test_mirrors.py",
             "ros2_ws/src/body_scheme_apps/test/test_experiments_zoo.py"]
    done = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *files],
                          cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    collected = [line for line in done.stdout.splitlines() if "::" in line]
    assert [name.split("::")[1][:40] for name in collected[:3]] == [
        "test_a_run_with_flips_judges_the_learner", "test_with_mirror_hypotheses_a_body_whose",
        "test_with_mirror_hypotheses_a_body_whose"], done.stdout[-2000:]

def test_a_test_process_runs_its_math_library_on_one_thread():
    """conftest.py pins BLAS to one thread in every test process (two workers on two cores each with a thread per
    core ran the CPU-bound tests at half speed)."""
    import numpy  # noqa: F401  (its BLAS loaded, whenever it was first imported)
    from threadpoolctl import threadpool_info

    assert {pool["num_threads"] for pool in threadpool_info()} == {1}
