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
