"""What every command of ours does before its ``main``: one math-library thread (``BODY_SCHEME_MATH_THREADS``)."""

from __future__ import annotations

import functools
import pathlib
import signal
import sys

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.threads import limit_math_threads

__all__ = ["command"]


def command(main):
    """Wrap a console ``main(argv=None)``: limit the math threads first (:func:`limit_math_threads`); a bad
    ``BODY_SCHEME_MATH_THREADS`` is one line on stderr and exit code 2, not a traceback. An interrupt (Ctrl-C; SIGTERM
    while nodes run, see :mod:`body_scheme_nodes.graph`) is one line and the shell's exit code, 128 + the signal
    (130, 143), after the ``finally`` blocks stopped what the command started."""
    @functools.wraps(main)
    def run(argv=None):
        name = _name(main.__module__)
        try:
            limit_math_threads()
        except BodySchemeError as error:
            print(f"{name}: {error}", file=sys.stderr)
            return 2
        try:
            return main(argv)
        except KeyboardInterrupt as interrupt:  # named after its signal by body_scheme_nodes.graph, else Ctrl-C's
            signum = signal.Signals.__members__.get(str(interrupt), signal.SIGINT)
            print(f"{name}: interrupted ({signum.name})", file=sys.stderr)
            return 128 + signum

    return run


def _name(module):
    """The command's name: its module's (``calibrate``), its package's for a package's ``__main__``
    (``experiments``), also when run as ``python -m`` (``__main__``: from the path Python ran)."""
    parts = module.split(".")
    if parts == ["__main__"]:
        path = pathlib.Path(sys.argv[0])
        parts = [path.parent.name, path.stem]
    return parts[-2] if parts[-1] == "__main__" and len(parts) > 1 else parts[-1]
