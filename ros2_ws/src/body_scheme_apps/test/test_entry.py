"""Every command of ours limits its math threads before it starts, and a bad ``BODY_SCHEME_MATH_THREADS`` is one line
and exit code 2 (the benchmarks and experiments pin one thread themselves: their figures are single-core)."""

import importlib

import pytest

COMMANDS = ("calibrate", "core_demo", "fuzz", "live_demo", "load_bench", "other_stacks", "plan_markers", "record",
            "replay_offline")


@pytest.mark.parametrize("module", COMMANDS)
def test_a_bad_thread_count_is_one_line_and_exit_code_2(module, monkeypatch, capsys):
    main = importlib.import_module(f"body_scheme_apps.{module}").main
    monkeypatch.setenv("BODY_SCHEME_MATH_THREADS", "many")
    assert main(["--help"]) == 2  # refused before the arguments are read
    err = capsys.readouterr().err
    assert err == f"{module}: BODY_SCHEME_MATH_THREADS must be a positive integer, got 'many'\n"


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
