"""One math-library thread per process: what every process of ours runs with, unless the user asks otherwise.

numpy's BLAS (OpenBLAS here) starts one thread per core. Our processes run side by side (scheme_node, tracker_node,
sim_node, a replay, a demo's four nodes) and their matrices are small, so those threads only fight over the cores:
on a loaded two-core machine the demo then missed a blocked joint, and the offline replay took 44 s of CPU instead of
19 s (issue 36). The benchmarks and experiments always measured with one thread.

:func:`limit_math_threads` sets the thread pools of the libraries already loaded (threadpoolctl) and the environment
variables that the libraries loaded later, and the processes this one starts, read. ``BODY_SCHEME_MATH_THREADS``
(a positive integer) overrides the default of one for a process and its children.
"""

from __future__ import annotations

import os

from .errors import InvalidInputError

__all__ = ["MATH_THREAD_VARIABLES", "THREADS_VARIABLE", "limit_math_threads", "math_threads_wanted"]

#: The environment variables the math libraries read when they load (OpenMP, OpenBLAS, MKL, BLIS).
MATH_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
#: The user's choice of threads per process (default 1).
THREADS_VARIABLE = "BODY_SCHEME_MATH_THREADS"


def math_threads_wanted(environ=None):
    """The threads per process the user asked for in ``BODY_SCHEME_MATH_THREADS`` (default 1)."""
    text = (os.environ if environ is None else environ).get(THREADS_VARIABLE, "1").strip()
    try:
        threads = int(text)
    except ValueError:
        threads = 0
    if threads < 1:
        raise InvalidInputError(f"{THREADS_VARIABLE} must be a positive integer, got {text!r}")
    return threads


def limit_math_threads(threads=None):
    """Limit this process's (and its children's) math-library thread pools to ``threads`` (default:
    :func:`math_threads_wanted`); returns the number of threads set."""
    threads = math_threads_wanted() if threads is None else int(threads)
    if threads < 1:
        raise InvalidInputError(f"threads must be a positive integer, got {threads!r}")
    for name in MATH_THREAD_VARIABLES:
        os.environ[name] = str(threads)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=threads)
    return threads
