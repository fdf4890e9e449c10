"""The applications' commands: the core demo end to end, and the aliases that keep the old command names working."""

from __future__ import annotations

import ast
import importlib.util
import pathlib
import subprocess
import sys

import pytest
from body_scheme_apps import core_demo

SRC = pathlib.Path(__file__).resolve().parents[2]


def test_core_demo_runs_end_to_end(capsys):
    """core_demo bootstraps, detects the blocked joint, repairs and reinstates (short run)."""
    assert core_demo.main(["--steps", "270", "--seed", "1"]) == 0
    out = capsys.readouterr().out
    assert "Structure recovered exactly: yes" in out
    assert "mismatch_detected" in out and "model_replaced" in out and out.count("model_reinstated") >= 2


def _aliases():
    """``{alias module path: target module}`` of every alias module in the libraries (a module with ``TARGET``)."""
    found = {}
    for path in sorted(SRC.glob("body_scheme_*/body_scheme_*/*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Assign) and [getattr(t, "id", None) for t in node.targets] == ["TARGET"]:
                found[path] = node.value.value
    return found


def test_every_moved_command_has_an_alias_to_an_existing_module():
    aliases = _aliases()
    assert {f"{p.parent.name}.{p.stem}" for p in aliases} == {
        "body_scheme_core.bench", "body_scheme_core.demo", "body_scheme_nodes.replay_offline",
        "body_scheme_sim.experiments", "body_scheme_sim.live_demo", "body_scheme_sim.record", "body_scheme_sim.bench",
        "body_scheme_sim.sim_node"}
    for target in aliases.values():
        assert importlib.util.find_spec(target) is not None, target


@pytest.mark.parametrize("old, new", [("body_scheme_sim.record", "body_scheme_apps.record"),
                                      ("body_scheme_nodes.replay_offline", "body_scheme_apps.replay_offline")])
def test_an_alias_runs_its_target_with_the_same_arguments_and_exit_code(old, new):
    """``python -m OLD --help`` prints NEW's help and exits 0; a bad option exits 2 like NEW does."""
    def run(module, *argv):
        return subprocess.run([sys.executable, "-m", module, *argv], capture_output=True, text=True, timeout=120)

    old_help, new_help = run(old, "--help"), run(new, "--help")
    assert old_help.returncode == new_help.returncode == 0
    assert old_help.stdout.split("\n", 1)[1] == new_help.stdout.split("\n", 1)[1]  # the usage line names the program
    assert run(old, "--no-such-option").returncode == 2
