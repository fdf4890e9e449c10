"""Every ``ros2 run`` executable of the packages names a module of its own package with a ``main``, once."""

from __future__ import annotations

import importlib

from workspace import console_scripts


def test_every_executable_runs_a_main_of_its_own_package():
    scripts = console_scripts()
    assert len(scripts) >= 10
    for package, name, target in scripts:
        module, function = target.split(":")
        assert module.split(".")[0] == package, f"{package}'s {name} runs {module}, another package's module"
        assert callable(getattr(importlib.import_module(module), function)), target
    names = [(package, name) for package, name, _ in scripts]
    assert len(names) == len(set(names))
