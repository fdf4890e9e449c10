"""The suite's own scheduling: what ``make test`` runs first."""

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
