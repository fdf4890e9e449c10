"""Every command in a ``bash`` block of README.md and docs/*.md names what exists and passes options it accepts, as
written: ``make`` targets (and the variables their recipes use), our modules' and executables' command lines (parsed
by their own parsers), node parameters (``-p name:=value``, ``--params-file``), launch files and their arguments, and
the ``body-scheme`` command; and docs/nodes.md names every parameter of every node, lists none a node lacks, and
gives the nodes' defaults. What the commands print and do is tested where they are (the system tests, test_cli,
test_plan_markers, test_replay_offline, ...); these tests fail when a doc and the code drift apart."""

from __future__ import annotations

import argparse
import ast
import importlib
import os
import re
import subprocess

import pytest
import yaml
from rclpy.parameter import Parameter
from workspace import REPO, SRC, console_scripts, documented_commands

from body_scheme_nodes import cli
from body_scheme_nodes.settings import parameter_defaults

OURS = {path.name for path in SRC.iterdir() if (path / "package.xml").is_file()}
#: Commands of other tools, which the docs show and this test does not check.
OTHER_TOOLS = {"source", "pip", "cd", "cat", "head", "grep", "colcon"}
OTHER_PACKAGES = {"usb_cam", "camera_calibration"}
COMMANDS = documented_commands()


def _ids(commands):
    return [f"{doc}: {' '.join(words)[:70]}" for doc, words in commands]


def _of_kind(*prefix):
    chosen = [(doc, words) for doc, words in COMMANDS if tuple(words[:len(prefix)]) == prefix
              and not (words[0] == "ros2" and words[2] in OTHER_PACKAGES)]
    return pytest.mark.parametrize("doc, words", chosen, ids=_ids(chosen))


class _Parsed(BaseException):
    """Raised by the patched ``parse_args`` once a command line was accepted: nothing after it runs."""


@pytest.fixture
def parse_only(monkeypatch):
    """Make every ArgumentParser stop right after it accepted its command line (:class:`_Parsed`)."""
    original = argparse.ArgumentParser.parse_args

    def parse(self, args=None, namespace=None):
        raise _Parsed(original(self, args, namespace))

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse)


def _accepts(module_name, argv):
    """Whether ``module_name``'s ``main`` accepts ``argv`` (parsing only); its usage error otherwise."""
    module = importlib.import_module(module_name)
    if not hasattr(module, "main"):
        module = importlib.import_module(module_name + ".__main__")
    try:
        module.main(argv)
    except _Parsed:
        return
    except SystemExit as exited:
        pytest.fail(f"{module_name} refused {argv}: exit {exited.code}")
    pytest.fail(f"{module_name}.main({argv}) ran without parsing a command line")


def _console_scripts(package):
    """``{executable: module}`` of ``package``."""
    return {name: target.split(":")[0] for owner, name, target in console_scripts() if owner == package}


def _parameters(executable):
    """``{name: default or None}``: a node's parameters as it declares them (None: a default that is not a literal),
    and those of its shipped YAML (a test keeps it equal to the declared defaults; scheme_node's holds the example
    arm's ids and joints: its declared defaults are ``parameter_defaults``)."""
    module = _console_scripts("body_scheme_nodes")[executable]
    source = (SRC / "body_scheme_nodes" / (module.replace(".", "/") + ".py")).read_text(encoding="utf-8")
    declared = {name: _literal(default)
                for name, default in re.findall(r'declare_parameter\(\s*"([\w.]+)",\s*([^)]*)\)', source)}
    config = SRC / "body_scheme_nodes" / "config" / f"{executable}.yaml"
    shipped = _yaml_parameters(config) if config.is_file() else {}
    if executable == "scheme_node":
        shipped.update(parameter_defaults())
    return {**declared, **shipped}


def _literal(text):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return None  # a name, not a literal: unknown here


def _yaml_parameters(path):
    def flat(mapping, prefix=""):
        for key, value in mapping.items():
            if isinstance(value, dict):
                yield from flat(value, f"{prefix}{key}.")
            else:
                yield prefix + key, value

    return {name: value for node in yaml.safe_load(path.read_text(encoding="utf-8")).values()
            for name, value in flat(node["ros__parameters"])}


def _ros_type(value, what):
    """The ROS parameter type a YAML value gets (``0`` is an integer: a double parameter refuses it; ``[0, 0.5]``
    has none: rcl refuses it)."""
    try:
        return Parameter.Type.from_parameter_value(value)
    except TypeError:
        pytest.fail(f"{what}: no ROS parameter type holds {value!r} (a list must be of one type: 0.0, not 0)")


def _our_file(path):
    """The file ``path`` names in our tree (given from the repository or from ros2_ws/), or None for a user's."""
    for base in (REPO, REPO / "ros2_ws"):
        if path.startswith(("ros2_ws/", "src/body_scheme", "bags/")) and (base / path).exists():
            return base / path
    return None


def test_every_documented_command_is_checked_here():
    assert len(COMMANDS) >= 40
    kinds = {words[0] for _, words in COMMANDS}
    assert kinds <= OTHER_TOOLS | {"make", "python", "ros2", "body-scheme"}, kinds
    for doc, words in COMMANDS:
        if words[0] == "python":
            assert words[1] == "-m", (doc, words)
        if words[0] == "ros2":
            assert words[1] in ("run", "launch") and (words[2] in OURS or words[2] in OTHER_PACKAGES), (doc, words)


@_of_kind("make")
def test_make_targets_exist_and_use_the_variables_given(doc, words):
    assignments = [word for word in words[1:] if "=" in word]
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}  # not the CI's make
    dry_run = subprocess.run(["make", "-n", *words[1:]], cwd=REPO, env=env, capture_output=True, text=True,
                             check=False)
    assert dry_run.returncode == 0, (doc, words, dry_run.stderr)
    for assignment in assignments:
        assert assignment.split("=", 1)[1] in dry_run.stdout, f"{doc}: make {words[1]} does not use {assignment}"


@_of_kind("python", "-m")
def test_our_modules_accept_their_documented_command_lines(doc, words, parse_only):
    _accepts(words[2], words[3:])


@_of_kind("body-scheme")
def test_the_cli_accepts_its_documented_command_lines(doc, words):
    cli.parser().parse_args(words[1:])


@_of_kind("ros2", "run")
def test_ros2_run_names_our_executables_and_their_parameters(doc, words, parse_only):
    package, executable, argv = words[2], words[3], words[4:]
    scripts = _console_scripts(package)
    assert executable in scripts, f"{doc}: {package} has no executable {executable}"
    if package != "body_scheme_nodes":  # an application: its own command line
        _accepts(scripts[executable], argv)
        return
    parameters = _parameters(executable)
    assert argv[:1] in ([], ["--ros-args"]), (doc, words)
    for flag, value in zip(argv[1::2], argv[2::2], strict=True):
        if flag == "-p":
            name, text = value.split(":=", 1)
            assert name in parameters, f"{doc}: {executable} has no parameter {name}"
            default = parameters[name]
            if "<" in text:  # "<...>" is a placeholder for the user's value
                continue
            given = _ros_type(yaml.safe_load(text), f"{doc}: {name}:={text}")
            if default not in (None, []):  # an empty list's type is the node's declaration
                assert given == _ros_type(default, name), (
                    f"{doc}: {name}:={text} is not of {name}'s type (default {default!r})")
        elif flag == "--params-file" and _our_file(value) is not None:
            unknown = set(_yaml_parameters(_our_file(value))) - set(parameters)
            assert not unknown, f"{doc}: {value} sets parameters {executable} lacks: {sorted(unknown)}"
        else:
            assert flag in ("--params-file", "-r"), (doc, flag)


@_of_kind("ros2", "launch")
def test_ros2_launch_names_our_launch_files_and_their_arguments(doc, words):
    package, name = words[2], words[3]
    launch = SRC / package / "launch" / name
    assert launch.is_file(), f"{doc}: {package} has no launch file {name}"
    declared = set(re.findall(r'DeclareLaunchArgument\(\s*"(\w+)"', launch.read_text(encoding="utf-8")))
    for argument in words[4:]:
        assert argument.split(":=")[0] in declared, f"{doc}: {name} declares no argument {argument}"


def _node_sections():
    """``{node: its section of docs/nodes.md}``."""
    text = (REPO / "docs" / "nodes.md").read_text(encoding="utf-8")
    scripts = _console_scripts("body_scheme_nodes")
    sections = {}
    for section in re.split(r"^## ", text, flags=re.M)[1:]:
        name = section.split(maxsplit=1)[0]
        if name in scripts:
            sections[name] = section
    return sections


def _table_rows(section):
    """``[(names, default cell)]`` of the section's parameter table."""
    table = section[section.index("### Parameters"):]
    return [(re.findall(r"`([\w.]+)`", cells[1]), cells[3].strip())
            for cells in (line.split("|") for line in table.splitlines() if line.startswith("| `"))]


def test_docs_name_every_parameter_of_every_node_and_no_other():
    sections = _node_sections()
    assert {"scheme_node", "control_node", "babble_node", "tracker_node", "sim_node", "bag_replay"} <= set(sections)
    for node, section in sections.items():
        parameters = _parameters(node)
        assert parameters, node
        for name in parameters:
            if name.startswith("learner.") and "`learner.<field>`" in section:
                continue
            assert f"`{name}`" in section, f"docs/nodes.md's {node} section does not name its parameter {name}"
        for names, _ in _table_rows(section):
            for name in names:
                assert name in parameters, f"docs/nodes.md's {node} table lists {name}, which {node} lacks"


def test_the_docs_defaults_are_the_nodes_defaults():
    compared = 0
    for node, section in _node_sections().items():
        parameters = _parameters(node)
        for names, cell in _table_rows(section):
            if len(names) != 1 or parameters.get(names[0]) is None or " " in cell.strip("`"):
                continue  # several names, a default the source computes, or a default in words
            documented = yaml.safe_load(cell.strip("`").replace('""', "''"))
            assert documented == parameters[names[0]], f"docs/nodes.md: {node}'s {names[0]} defaults to " \
                                                        f"{parameters[names[0]]!r}, not {cell}"
            compared += 1
    assert compared >= 50
