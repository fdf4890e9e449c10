"""Every test process (pytest and each xdist worker) runs numpy's BLAS on one thread, as every process of ours does
(:mod:`body_scheme_core.threads`; ``BODY_SCHEME_MATH_THREADS`` overrides it): with a thread per core in each of two
workers on two cores they fought over the cores, and the zoo's flips test took 81 s in CI, 40 s alone with two
threads and 20 s with one."""

from body_scheme_core.threads import limit_math_threads


def pytest_configure(config):
    limit_math_threads()
