"""How the suite itself runs: what ``make test`` runs first, and on how many math threads."""

import subprocess
import sys

import pytest
from workspace import REPO


@pytest.mark.slow  # 2 s: a pytest collection; make test's order
def test_heavy_system_tests_are_collected_first_the_longest_first():
    """pytest-xdist hands tests out in collection order: the heavy ones first (tests/conftest.py), or the your-robot
    rehearsal, collected last by name, runs alone at the end of ``make test`` while the other worker idles."""
    files = ["tests/test_system_babble_node.py", "tests/test_system_your_robot.py"]
    done = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *files],
                          cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    collected = [line for line in done.stdout.splitlines() if "::" in line]
    assert [name.split("::")[1][:40] for name in collected[:3]] == [
        "test_the_simulated_rehearsal_runs_the_gr", "test_the_rehearsal_plans_babbles_over_th",
        "test_babbling_a_controller_learns_the_tr"], done.stdout[-2000:]


def test_a_test_process_runs_its_math_library_on_one_thread():
    """conftest.py pins BLAS to one thread in every test process (two workers on two cores each with a thread per
    core ran the CPU-bound tests at half speed)."""
    import numpy  # noqa: F401  (its BLAS loaded, whenever it was first imported)
    from threadpoolctl import threadpool_info

    assert {pool["num_threads"] for pool in threadpool_info()} == {1}
