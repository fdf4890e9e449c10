"""Saving and loading a learner's complete state as one JSON document, atomically and without executing code.

File layout (see ``docs/core/state-file-format.md``)::

    {"format": "body_scheme_state", "version": 1, "core_version": "0.1.0",
     "saved_at": "2025-01-01T12:00:00+00:00", "state": {...BodySchemeLearner.to_state()...}}

Writing goes to a temporary file in the destination directory, which is flushed and fsync'ed and then renamed over
the destination with :func:`os.replace`, so a crash leaves either the old or the new file, never a torn one.
Reading uses :mod:`json` only (never pickle) and turns every problem into a
:class:`~body_scheme_core.errors.ModelFileError` that says what is wrong.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import tempfile

from .. import __version__
from ..errors import ModelFileError
from .learner import BodySchemeLearner

__all__ = ["save_state", "encode_state", "write_state_text", "load_state", "STATE_FORMAT", "STATE_FILE_VERSION"]

#: Value of the ``format`` tag of a state file.
STATE_FORMAT = "body_scheme_state"
#: Version of the file layout written by :func:`save_state`; files of a newer version are refused.
STATE_FILE_VERSION = 1


def save_state(learner, path):
    """Write ``learner``'s complete state to ``path`` atomically.

    Parameters
    ----------
    learner : BodySchemeLearner
    path : str or os.PathLike
        Destination file; its directory must exist. An existing file is replaced.

    Returns
    -------
    path : str
        The absolute path written.
    """
    return write_state_text(encode_state(learner, path), path)


def encode_state(learner, path="<memory>"):
    """``learner``'s complete state as the text of a state file (``path`` only names it in errors).

    The only step that reads the learner: a node holds its learner lock for this and writes the text after
    (:func:`write_state_text`).
    """
    if not isinstance(learner, BodySchemeLearner):
        raise TypeError(f"learner must be a BodySchemeLearner, got {type(learner).__name__}")
    document = {
        "format": STATE_FORMAT,
        "version": STATE_FILE_VERSION,
        "core_version": __version__,
        "saved_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "state": learner.to_state(),
    }
    # allow_nan=False: NaN/inf are not JSON; a state containing them is refused here, with a clear error.
    try:
        return json.dumps(document, allow_nan=False, separators=(",", ":"))
    except ValueError as exc:
        raise ModelFileError(f"cannot save the learner's state to {os.fspath(path)!r}: it contains NaN or infinite "
                             f"values ({exc})") from exc


def write_state_text(text, path):
    """Write the text of a state file (:func:`encode_state`) to ``path`` atomically and durably; returns the absolute
    path."""
    path = os.path.abspath(os.fspath(path))
    directory = os.path.dirname(path)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{os.path.basename(path)}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_directory(directory)
    return path


def _fsync_directory(directory):
    """Make the rename durable where the platform allows it (POSIX); silently skipped elsewhere."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _reject_constant(name):
    raise ModelFileError(f"state file contains {name}, which is not valid JSON (NaN or infinite values)")


def _finite_float(text):
    """JSON number -> float, refusing numbers that overflow to infinity (``1e999``)."""
    value = float(text)
    if not math.isfinite(value):
        raise ModelFileError(f"state file contains the number {text}, which is not finite")
    return value


#: Longest integer a state file may hold (int64 has 19 digits); Python refuses to parse beyond 4,300 digits anyway.
MAX_INTEGER_DIGITS = 20


def _bounded_int(text):
    """JSON integer -> int, refusing numbers longer than :data:`MAX_INTEGER_DIGITS` before converting them."""
    if len(text.lstrip("-")) > MAX_INTEGER_DIGITS:
        raise ModelFileError(f"state file contains an integer of {len(text)} characters; at most "
                             f"{MAX_INTEGER_DIGITS} digits are allowed")
    return int(text)


def load_state(path):
    """Read a state file written by :func:`save_state` and rebuild the learner.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    learner : BodySchemeLearner

    Raises
    ------
    ModelFileError
        If the file is missing or unreadable, is not (complete) JSON, has another format tag, was written by a
        newer file version, misses keys, or holds arrays of the wrong shape or with NaN/inf values.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        raise ModelFileError(f"state file {path!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"cannot read state file {path!r}: {exc}") from exc
    if not text.strip():
        raise ModelFileError(f"state file {path!r} is empty")
    try:
        document = json.loads(text, parse_constant=_reject_constant, parse_float=_finite_float,
                              parse_int=_bounded_int)
    except ModelFileError as exc:
        raise ModelFileError(f"state file {path!r}: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ModelFileError(
            f"state file {path!r} is not valid JSON (truncated or corrupt?): {exc.msg} at line {exc.lineno} "
            f"column {exc.colno} of {len(text)} characters") from exc
    except RecursionError as exc:
        raise ModelFileError(f"state file {path!r} is nested too deeply to be a state file") from exc
    except ValueError as exc:  # numbers Python will not convert, whatever the parser's hooks
        raise ModelFileError(f"state file {path!r} holds a number that cannot be read: {exc}") from exc
    if not isinstance(document, dict):
        raise ModelFileError(f"state file {path!r} must hold a JSON object, got {type(document).__name__}")
    if document.get("format") != STATE_FORMAT:
        raise ModelFileError(
            f"{path!r} is not a body scheme state file: format tag {document.get('format')!r}, expected "
            f"{STATE_FORMAT!r}")
    version = document.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise ModelFileError(f"state file {path!r} has an invalid version {version!r}")
    if version > STATE_FILE_VERSION:
        raise ModelFileError(
            f"state file {path!r} has version {version}, written by a newer body_scheme_core "
            f"({document.get('core_version')!r}); this one ({__version__}) reads up to version {STATE_FILE_VERSION}")
    if "state" not in document:
        raise ModelFileError(f"state file {path!r} has no 'state'; keys: {sorted(document)}")
    try:
        return BodySchemeLearner.from_state(document["state"])
    except ModelFileError as exc:
        raise ModelFileError(f"state file {path!r}: {exc}") from exc
    except (RecursionError, MemoryError, ArithmeticError, LookupError, TypeError, ValueError) as exc:
        # state_file.from_dict checks every field; anything it lets through is still a bad file, never a crash
        raise ModelFileError(f"state file {path!r}: bad learner state: {type(exc).__name__}: {exc}") from exc
