"""scheme_node's checkpoint file: one regular file for one node, restored at start, written atomically. No ROS imports.

- ``checkpoint_path`` must be a regular file or not exist yet; a directory or a device is refused at start
  (:class:`CheckpointError`), never renamed or replaced. A symlink is followed: the file it points to is read and
  written in place (through a temporary file beside the target), so the link stays a link.
- A lock file ``<checkpoint>.lock`` (``flock``, released by the kernel when the process dies, also on ``kill -9``) is
  held for the node's lifetime: a second node on the same checkpoint refuses to start, naming the first one's pid.
  The lock file is opened where it is, never through a symlink (``O_NOFOLLOW``), and must be a regular file of one
  name; a checkpoint with several names (hard links) is refused too, since two lock files could then guard one
  file. Any of these, or a lock that cannot be made (a directory, a FIFO, a read-only place), is one
  :class:`CheckpointError`: one FATAL line at start. :func:`lock_holder` tells ``~/save`` that a file is another
  node's checkpoint, which it then never overwrites.
- Temporary files of our own writes (``.<name>.<random>.tmp``) that a kill left behind are removed at start: the
  checkpoint's own (we hold its lock), and in the state directory those that hold a state file's beginning (or
  nothing) and are older than :data:`ORPHAN_AGE` (a running node's save takes well under a second).
- :meth:`Checkpoint.restore` reads the file; a file that fails for *any* reason is moved aside to
  ``<checkpoint>.corrupt-<time>`` (never overwritten: a newer version's state survives a rollback), so a supervisor
  that restarts the node does not restart it into the same failure.
"""

from __future__ import annotations

import errno
import fcntl
import os
import pathlib
import re
import stat
import time

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning import write_state_text

from .state_files import SIGNATURE, check_loadable

__all__ = ["CheckpointError", "Checkpoint", "lock_holder", "remove_orphans", "ORPHAN_AGE"]

#: A temporary file of another writer in the state directory is an orphan once it is this old (s).
ORPHAN_AGE = 60.0
#: ``tempfile.mkstemp``'s names as ``write_state_text`` makes them: ``.<name>.<8 random characters>.tmp``.
_TEMPORARY = re.compile(r"\.(?P<name>.+)\.[A-Za-z0-9_]{8}\.tmp")


class CheckpointError(InvalidInputError):
    """The checkpoint path cannot be used (not a regular file, or in use by another node)."""


class Checkpoint:
    """The checkpoint file at ``path`` (see the module docstring); :meth:`close` releases its lock."""

    def __init__(self, path):
        requested = pathlib.Path(path).expanduser()
        #: Where the state is read and written: the symlink's target for a symlink.
        self.path = pathlib.Path(os.path.realpath(requested))
        self.followed_symlink = requested.is_symlink()
        try:
            info = os.stat(self.path)
        except FileNotFoundError:
            info = None
        if info is not None and not stat.S_ISREG(info.st_mode):
            kind = "a directory" if stat.S_ISDIR(info.st_mode) else "not a regular file"
            raise CheckpointError(f"checkpoint_path {str(path)!r} is {kind}; it must be a state file or not exist")
        if info is not None and info.st_nlink > 1:
            raise CheckpointError(f"checkpoint_path {str(path)!r} has {info.st_nlink} names (hard links): another node "
                                  f"may use it under another name; give this node a file of its own")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise CheckpointError(f"checkpoint_path {str(path)!r}: its directory cannot be made "
                                  f"({error.strerror})") from None
        self._lock = _lock(_lock_path(self.path))
        self.removed_orphans = remove_orphans(self.path.parent, own=self.path.name)

    def exists(self):
        return self.path.exists()

    def restore(self, load, max_bytes):
        """``(learner, None)`` from ``load(path)``, or ``(None, why)`` after moving a bad file aside.

        ``load`` is any callable returning a learner or raising; every exception counts as a bad file (the file is
        untrusted input, and the node must start). ``why`` is None when there is no file.
        """
        if not self.exists():
            return None, None
        try:
            check_loadable(self.path, max_bytes)
            return load(self.path), None
        except Exception as error:  # any failure of an untrusted file: moved aside, never a crash loop
            return None, self.move_aside(f"{type(error).__name__}: {error}")

    def move_aside(self, problem):
        """Rename the file to ``<checkpoint>.corrupt-<time>``; returns the sentence for the log."""
        aside = f"{self.path}.corrupt-{time.strftime('%Y%m%dT%H%M%S')}"
        try:
            os.replace(self.path, aside)
        except OSError as error:
            return f"{problem}; it cannot be moved aside ({error.strerror})"
        return f"{problem}; moved to {aside}"

    def write(self, text):
        """Write the state text atomically at :attr:`path` (the symlink's target for a symlink)."""
        return write_state_text(text, self.path)

    def close(self):
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None


def _lock_path(path):
    return pathlib.Path(f"{path}.lock")


def _open_lock(path, flags):
    """A descriptor of the lock file ``path``, opened where it is (``O_NOFOLLOW``): a regular file of one name, or
    CheckpointError."""
    try:
        fd = os.open(path, flags | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
    except OSError as error:
        why = "it is a symlink (a lock is never followed)" if error.errno == errno.ELOOP else error.strerror
        raise CheckpointError(f"the checkpoint's lock file {str(path)!r} cannot be used: {why}") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
        os.close(fd)
        kind = "not a regular file" if not stat.S_ISREG(info.st_mode) else f"a file of {info.st_nlink} names"
        raise CheckpointError(f"the checkpoint's lock file {str(path)!r} cannot be used: it is {kind}")
    return fd


def _lock(path):
    """An exclusive ``flock`` on ``path`` (created), holding our pid; refused while another process holds it."""
    fd = _open_lock(path, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise CheckpointError(f"checkpoint {str(path)[:-5]!r} is in use by another process (pid {holder}): two "
                              f"nodes must not share one checkpoint; give each its own checkpoint_path") from None
    except OSError as error:
        os.close(fd)
        raise CheckpointError(f"the checkpoint's lock file {str(path)!r} cannot be locked: {error.strerror}") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd


def lock_holder(path):
    """The pid (str) of the process that holds the lock of checkpoint ``path``, "unknown" if it cannot be read or
    the lock file is not one we would make, or None when no node holds it. A process's own checkpoint counts as
    held (flock locks belong to an open file, not a process)."""
    lock = _lock_path(path)
    if not os.path.lexists(lock):
        return None
    try:
        fd = _open_lock(lock, os.O_RDONLY)
    except CheckpointError:
        return "unknown"
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
    finally:
        os.close(fd)  # closing releases our shared lock
    return None


def remove_orphans(directory, own=None, now=None):
    """Remove temporary files of our writes in ``directory`` that a killed writer left; returns their names.

    ``own``'s temporary files are removed whatever their age (the caller holds its lock); others only when they are
    older than :data:`ORPHAN_AGE` and hold the beginning of a state file or nothing.
    """
    now = time.time() if now is None else now
    removed = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    for entry in entries:
        match = _TEMPORARY.fullmatch(entry.name)
        if match is None or not entry.is_file(follow_symlinks=False):
            continue
        try:
            if match["name"] != own:
                if now - entry.stat(follow_symlinks=False).st_mtime < ORPHAN_AGE:
                    continue
                with open(entry.path, "rb") as stream:
                    head = stream.read(len(SIGNATURE))
                if head and head != SIGNATURE:
                    continue
            os.unlink(entry.path)
            removed.append(entry.name)
        except OSError:
            continue
    return removed
