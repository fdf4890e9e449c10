"""The checkpoint file: a regular file or none, a symlink followed in place, one node per checkpoint (a lock), orphaned
temporary files removed, and any failure of a restored file moved aside."""

import os
import time

import pytest

from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.persistence import encode_state, load_state
from body_scheme_nodes.checkpoint import ORPHAN_AGE, Checkpoint, CheckpointError, lock_holder, remove_orphans


def _state_text():
    return encode_state(BodySchemeLearner([1, 2, 3], 2))


def test_a_directory_is_refused_and_left_as_it_is(tmp_path):
    directory = tmp_path / "state.json"
    directory.mkdir()
    (directory / "keep.txt").write_text("mine")
    with pytest.raises(CheckpointError, match="is a directory"):
        Checkpoint(directory)
    assert (directory / "keep.txt").read_text() == "mine" and not list(tmp_path.glob("*.corrupt-*"))


def test_a_symlink_is_followed_and_written_in_place(tmp_path):
    target = tmp_path / "real" / "state.json"
    target.parent.mkdir()
    link = tmp_path / "state.json"
    link.symlink_to(target)
    checkpoint = Checkpoint(link)
    try:
        assert checkpoint.path == target and checkpoint.followed_symlink
        checkpoint.write(_state_text())
        assert link.is_symlink() and target.is_file()
        assert load_state(link).part_ids == (1, 2, 3)
    finally:
        checkpoint.close()


def test_a_second_checkpoint_on_the_same_file_is_refused_until_the_first_is_closed(tmp_path):
    first = Checkpoint(tmp_path / "state.json")
    with pytest.raises(CheckpointError, match=f"in use by another process \\(pid {os.getpid()}\\)"):
        Checkpoint(tmp_path / "state.json")
    first.close()
    Checkpoint(tmp_path / "state.json").close()


def test_a_lock_file_is_never_followed_and_every_lock_failure_is_a_checkpoint_error(tmp_path, monkeypatch):
    """A symlinked lock file (a user's file became our pid before), a directory or a FIFO in its place, a lock that
    cannot be made: each is a CheckpointError (one FATAL line at start), and the user's file is untouched."""
    users = tmp_path / "users_file.txt"
    users.write_text("mine")
    (tmp_path / "a.json.lock").symlink_to(users)
    with pytest.raises(CheckpointError, match="symlink"):
        Checkpoint(tmp_path / "a.json")
    assert users.read_text() == "mine"
    (tmp_path / "b.json.lock").mkdir()
    with pytest.raises(CheckpointError, match="b.json.lock"):
        Checkpoint(tmp_path / "b.json")
    os.mkfifo(tmp_path / "c.json.lock")
    with pytest.raises(CheckpointError, match="not a regular file"):
        Checkpoint(tmp_path / "c.json")

    def read_only(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "open", read_only)
    with pytest.raises(CheckpointError, match="Permission denied"):
        Checkpoint(tmp_path / "d.json")


def test_a_checkpoint_of_several_names_is_refused_and_a_held_one_is_named(tmp_path):
    """A hard link to a checkpoint would let two lock files guard one file: refused. lock_holder names the process
    that holds a checkpoint (what ~/save asks before it writes), and nobody once it is closed."""
    first = Checkpoint(tmp_path / "arm.json")
    try:
        first.write(_state_text())
        os.link(tmp_path / "arm.json", tmp_path / "alias.json")
        with pytest.raises(CheckpointError, match="2 names"):
            Checkpoint(tmp_path / "alias.json")
        assert lock_holder(tmp_path / "arm.json") == str(os.getpid())
        assert lock_holder(tmp_path / "alias.json") is None and lock_holder(tmp_path / "none.json") is None
    finally:
        first.close()
    assert lock_holder(tmp_path / "arm.json") is None


def test_orphaned_temporary_files_of_our_writes_are_removed_and_nothing_else(tmp_path):
    old = time.time() - 2 * ORPHAN_AGE
    own = tmp_path / ".state.json.abc123_x.tmp"  # the checkpoint's own: removed whatever its age
    own.write_text("{\"format\":\"body_scheme_state\"")
    other_state = tmp_path / ".arm.json.k9k9k9k9.tmp"  # a ~/save's, old and ours: removed
    other_state.write_text(_state_text()[:100])
    os.utime(other_state, (old, old))
    young = tmp_path / ".arm2.json.y0y0y0y0.tmp"  # may be a running save: kept
    young.write_text(_state_text()[:100])
    foreign = tmp_path / ".notes.txt.abcdefgh.tmp"  # someone else's: kept
    foreign.write_text("other program")
    os.utime(foreign, (old, old))
    unrelated = tmp_path / "state.json.tmp"
    unrelated.write_text("x")
    checkpoint = Checkpoint(tmp_path / "state.json")
    checkpoint.close()
    assert sorted(checkpoint.removed_orphans) == sorted([own.name, other_state.name])
    assert young.exists() and foreign.exists() and unrelated.exists()
    assert remove_orphans(tmp_path) == []


@pytest.mark.parametrize("content", ['{"format":"body_scheme_state","version":1,"state":{"step":' + "9" * 5000 + "}}",
                                     "[" * 100_000, "\x00\xff garbage"])
def test_a_file_that_fails_for_any_reason_is_moved_aside(tmp_path, content):
    path = tmp_path / "state.json"
    path.write_text(content)
    checkpoint = Checkpoint(path)
    try:
        learner, problem = checkpoint.restore(load_state, 1 << 20)
    finally:
        checkpoint.close()
    assert learner is None and "moved to" in problem
    (aside,) = tmp_path.glob("state.json.corrupt-*")
    assert aside.read_text() == content and not path.exists()


def test_an_unexpected_exception_of_the_loader_is_a_bad_file_too(tmp_path):
    path = tmp_path / "state.json"
    path.write_text(_state_text())

    def broken(_):
        raise ZeroDivisionError("a defect the file triggered")

    checkpoint = Checkpoint(path)
    try:
        learner, problem = checkpoint.restore(broken, 1 << 20)
        assert learner is None and "ZeroDivisionError" in problem and not path.exists()
        assert checkpoint.restore(load_state, 1 << 20) == (None, None)  # no file any more: a fresh start
    finally:
        checkpoint.close()
