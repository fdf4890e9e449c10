"""Where scheme_node's ``~/save`` and ``~/load`` may touch files: names inside one state directory, nothing else.

Anyone in the ROS domain can call these services, so a requested name is resolved inside ``state_dir`` and refused
if it leaves it (absolute paths elsewhere, ``..``, symlinks pointing out), if it is not a regular file (a FIFO would
block the node, ``/dev/zero`` would eat its memory), if it is larger than ``max_bytes``, or, when saving, if an
existing file there is not a body scheme state file or has several names (it is never overwritten); scheme_node
also refuses to save over another running node's checkpoint (:func:`~body_scheme_nodes.checkpoint.lock_holder`).
Error messages name only the request and the state directory, never anything about files outside it. No ROS imports.
"""

from __future__ import annotations

import os
import pathlib
import stat

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning import STATE_FORMAT

__all__ = ["StateFileError", "resolve", "check_loadable", "check_overwritable", "DEFAULT_MAX_BYTES", "SIGNATURE"]

#: Largest state file ``~/load`` reads (a 6-DOF arm's state is about 2 MB).
DEFAULT_MAX_BYTES = 64 * 1024 * 1024
#: A state file starts with this (``save_state`` writes the format tag first).
SIGNATURE = f'{{"format":"{STATE_FORMAT}"'.encode()


class StateFileError(InvalidInputError):
    """A requested state file name is refused."""


def resolve(state_dir, name):
    """The path of ``name`` inside ``state_dir``, all symlinks resolved.

    Raises
    ------
    StateFileError
        For an empty name, or one that resolves outside the state directory.
    """
    if not name:
        raise StateFileError("no file name given")
    root = pathlib.Path(state_dir).resolve()
    requested = pathlib.Path(name)
    path = (requested if requested.is_absolute() else root / requested).resolve()
    if path == root or root not in path.parents:
        raise StateFileError(f"{name!r} is not a file name inside the state directory {root}")
    return path


def check_loadable(path, max_bytes=DEFAULT_MAX_BYTES):
    """Refuse anything but an existing regular file of at most ``max_bytes`` (``path`` from :func:`resolve`)."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise StateFileError(f"{path.name!r} does not exist in the state directory") from None
    except OSError as error:
        raise StateFileError(f"{path.name!r} cannot be read: {error.strerror}") from None
    if not stat.S_ISREG(info.st_mode):
        raise StateFileError(f"{path.name!r} is not a regular file")
    if info.st_size > max_bytes:
        raise StateFileError(f"{path.name!r} is larger than the {max_bytes} byte limit of a state file")


def check_overwritable(path):
    """Refuse to replace an existing file that is not a body scheme state file, anything but a regular file, or a
    file of several names (hard links: the others would keep the old state, e.g. a running node's checkpoint)."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        return
    if not stat.S_ISREG(info.st_mode):
        raise StateFileError(f"{path.name!r} exists and is not a regular file; not overwritten")
    if info.st_nlink > 1:
        raise StateFileError(f"{path.name!r} has {info.st_nlink} names (hard links); not overwritten")
    with open(path, "rb") as stream:
        head = stream.read(len(SIGNATURE))
    if head != SIGNATURE:
        raise StateFileError(f"{path.name!r} exists and is not a body scheme state file; not overwritten")
