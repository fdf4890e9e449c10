"""~/save and ~/load names: confined to the state directory, regular files only, size-limited, foreign files kept."""

from __future__ import annotations

import os

import pytest

from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.persistence import load_state, save_state
from body_scheme_nodes.state_files import StateFileError, check_loadable, check_overwritable, resolve


@pytest.fixture
def state_dir(tmp_path):
    directory = tmp_path / "states"
    directory.mkdir()
    return directory


@pytest.mark.parametrize("name, message", [
    ("/etc/x.json", "not a file name inside the state directory"),
    ("../x.json", "not a file name inside the state directory"),
    ("a/../../x.json", "not a file name inside the state directory"),
    ("", "no file name"),
    (".", "not a file name inside"),
])
def test_names_leaving_the_state_directory_are_refused(state_dir, name, message):
    with pytest.raises(StateFileError, match=message):
        resolve(state_dir, name)


def test_names_inside_resolve_and_symlinks_out_are_refused(state_dir, tmp_path):
    assert resolve(state_dir, "robot.json") == (state_dir / "robot.json").resolve()
    assert resolve(state_dir, str(state_dir / "sub" / "robot.json")).parent.name == "sub"
    (state_dir / "shadow.json").symlink_to("/etc/passwd")
    (state_dir / "zero.json").symlink_to("/dev/zero")
    for name in ("shadow.json", "zero.json"):
        with pytest.raises(StateFileError, match="not a file name inside the state directory") as info:
            resolve(state_dir, name)
        assert "passwd" not in str(info.value) and "/dev" not in str(info.value)  # nothing about outside files


def test_only_regular_files_within_the_size_limit_are_loaded(state_dir):
    fifo = state_dir / "fifo.json"
    os.mkfifo(fifo)
    with pytest.raises(StateFileError, match="not a regular file"):
        check_loadable(resolve(state_dir, "fifo.json"))
    big = state_dir / "big.json"
    big.write_bytes(b"x" * 2000)
    with pytest.raises(StateFileError, match="larger than the 1000 byte limit"):
        check_loadable(resolve(state_dir, "big.json"), max_bytes=1000)
    with pytest.raises(StateFileError, match="does not exist"):
        check_loadable(resolve(state_dir, "missing.json"))


def test_a_foreign_file_is_never_overwritten_a_state_file_is(state_dir):
    foreign = state_dir / "notes.json"
    foreign.write_text('{"mine": true}')
    with pytest.raises(StateFileError, match="not a body scheme state file; not overwritten"):
        check_overwritable(resolve(state_dir, "notes.json"))
    assert foreign.read_text() == '{"mine": true}'
    ours = resolve(state_dir, "robot.json")
    check_overwritable(ours)  # does not exist yet: fine
    save_state(BodySchemeLearner([1, 2], 1), ours)
    check_overwritable(ours)  # ours: may be replaced
    check_loadable(ours)
    assert load_state(ours).part_ids == (1, 2) or list(load_state(ours).part_ids) == [1, 2]
    os.link(ours, state_dir / "alias.json")  # a second name: the other keeps the old state, so it is not replaced
    with pytest.raises(StateFileError, match="2 names"):
        check_overwritable(ours)
