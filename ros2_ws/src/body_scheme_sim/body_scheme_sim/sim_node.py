"""Alias of :mod:`body_scheme_nodes.sim_node`, where this command now lives (see docs/architecture.md).

Kept so that ``ros2 run body_scheme_sim sim_node``
keep working; it runs that module and imports nothing from it.
"""

import runpy

#: The module this alias runs.
TARGET = "body_scheme_nodes.sim_node"


def main():
    """Run :data:`TARGET` as ``__main__`` with this process's arguments."""
    runpy.run_module(TARGET, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
