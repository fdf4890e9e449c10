"""Every command of ours limits its math threads before it starts, and a bad ``BODY_SCHEME_MATH_THREADS`` is one line
and exit code 2 (the benchmarks and experiments then pin one thread themselves: their figures are single-core); an
interrupt is one line and the shell's exit code."""

import importlib
import os
import pkgutil
import subprocess
import sys

import pytest

import body_scheme_apps


def _commands():
    """``{name: module}`` of every module of body_scheme_apps with a ``main`` (a package's ``__main__`` by the
    package's name): the console scripts and the ``python -m`` commands the docs name."""
    found = {}
    for info in pkgutil.walk_packages(body_scheme_apps.__path__, "body_scheme_apps."):
        module = importlib.import_module(info.name)
        if callable(getattr(module, "main", None)):
            parts = info.name.split(".")
            found[parts[-2] if parts[-1] == "__main__" else parts[-1]] = info.name
    return found


COMMANDS = _commands()


def test_the_commands_are_found():
    assert {"calibrate", "experiments", "learning_bench", "perception_bench", "bootstrap_bench", "live_demo",
            "replay_offline"} <= set(COMMANDS)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_a_bad_thread_count_is_one_line_and_exit_code_2(name, monkeypatch, capsys):
    main = importlib.import_module(COMMANDS[name]).main
    monkeypatch.setenv("BODY_SCHEME_MATH_THREADS", "many")
    assert main(["--help"]) == 2  # refused before the arguments are read
    err = capsys.readouterr().err
    assert err == f"{name}: BODY_SCHEME_MATH_THREADS must be a positive integer, got 'many'\n"


@pytest.mark.parametrize("module, name", [("body_scheme_apps.experiments", "experiments"),
                                          ("body_scheme_apps.calibrate", "calibrate")])
def test_python_dash_m_names_the_command(module, name):
    """``python -m``: the module is ``__main__``; the name comes from the path Python ran (a package's
    ``__main__.py``: the package's)."""
    env = {**os.environ, "BODY_SCHEME_MATH_THREADS": "0"}
    done = subprocess.run([sys.executable, "-m", module, "--help"], env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    assert done.stderr == f"{name}: BODY_SCHEME_MATH_THREADS must be a positive integer, got '0'\n"


@pytest.mark.parametrize("interrupt, code, line", [(KeyboardInterrupt(), 130, "SIGINT"),
                                                    (KeyboardInterrupt("SIGTERM"), 143, "SIGTERM")])
def test_an_interrupt_is_one_line_and_the_shells_exit_code(interrupt, code, line, capsys):
    """Ctrl-C (or SIGTERM while nodes run: body_scheme_nodes.graph makes it an interrupt named after it) is one line
    naming the signal and exit code 128 + its number, after the command's finally blocks ran; no traceback."""
    from body_scheme_apps.entry import command

    stopped = []

    @command
    def main(argv=None):
        try:
            raise interrupt
        finally:
            stopped.append(True)

    main.__wrapped__.__module__ = "body_scheme_apps.live_demo"
    assert main([]) == code and stopped == [True]
    assert capsys.readouterr().err == f"live_demo: interrupted ({line})\n"
