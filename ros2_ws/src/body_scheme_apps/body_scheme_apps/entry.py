"""What every command of ours does before its ``main``: one math-library thread (``BODY_SCHEME_MATH_THREADS``)."""

from __future__ import annotations

import functools
import sys

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.threads import limit_math_threads

__all__ = ["command"]


def command(main):
    """Wrap a console ``main(argv=None)``: limit the math threads first (:func:`limit_math_threads`); a bad
    ``BODY_SCHEME_MATH_THREADS`` is one line on stderr and exit code 2, not a traceback."""

    @functools.wraps(main)
    def run(argv=None):
        try:
            limit_math_threads()
        except BodySchemeError as error:
            print(f"{main.__module__.rsplit('.', 1)[-1]}: {error}", file=sys.stderr)
            return 2
        return main(argv)

    return run
