"""One math-library thread per process (threads.py): the pools already loaded and the environment of what starts
later, in a fresh interpreter (a test must not change the thread pools of the test process)."""

import json
import os
import subprocess
import sys

import pytest

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.threads import THREADS_VARIABLE, math_threads_wanted

SCRIPT = r"""
import json, os, subprocess, sys
import numpy  # loaded before the limit: its pool is already started
from threadpoolctl import threadpool_info, threadpool_limits
from body_scheme_core.threads import limit_math_threads
threadpool_limits(limits=3)  # as a pool started on three cores would be (whatever this machine has)
before = [pool["num_threads"] for pool in threadpool_info()]
set_to = limit_math_threads()
after = [pool["num_threads"] for pool in threadpool_info()]
child = subprocess.run([sys.executable, "-c", "import os; print(os.environ['OPENBLAS_NUM_THREADS'])"],
                       capture_output=True, text=True).stdout.strip()
print(json.dumps({"before": before, "set_to": set_to, "after": after, "child": child}))
"""


def _run(threads=None):
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS") and k != THREADS_VARIABLE}
    if threads is not None:
        env[THREADS_VARIABLE] = threads
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def test_every_pool_gets_one_thread_and_so_do_the_processes_started_after():
    out = _run()
    assert out["set_to"] == 1 and out["after"] and set(out["after"]) == {1} and out["child"] == "1"
    assert set(out["before"]) == {3}  # what it replaced


def test_the_user_may_ask_for_more_and_nonsense_is_refused():
    two = _run("2")
    assert set(two["after"]) == {2} and two["child"] == "2"
    assert math_threads_wanted({}) == 1 and math_threads_wanted({THREADS_VARIABLE: " 3 "}) == 3
    for bad in ("0", "-1", "two", ""):
        with pytest.raises(InvalidInputError, match=THREADS_VARIABLE):
            math_threads_wanted({THREADS_VARIABLE: bad})
