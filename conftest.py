"""What every test process shares, whichever tests it runs.

- numpy's BLAS on one thread, as in every process of ours (:mod:`body_scheme_core.threads`;
  ``BODY_SCHEME_MATH_THREADS`` overrides it): with a thread per core in each of two pytest-xdist workers on two cores
  they fought over the cores, and the zoo's flips test took 81 s in CI, 40 s alone with two threads, 20 s with one.
- The tests marked ``heavy(seconds)`` first, the longest first: pytest-xdist hands tests out in collection order, so a
  20-s test collected late ran alone at the end while the other worker idled. The DDS system tests are not marked:
  the rendered graph's story depends on timing, and beside the your-robot rehearsal a CI run lost its tree.
"""

from body_scheme_core.threads import limit_math_threads


def pytest_configure(config):
    limit_math_threads()


def pytest_collection_modifyitems(config, items):
    def seconds(item):
        heavy = item.get_closest_marker("heavy")
        return heavy.kwargs["seconds"] if heavy else 0

    items.sort(key=lambda item: -seconds(item))
