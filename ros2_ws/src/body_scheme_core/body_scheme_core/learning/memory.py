"""Memory: the models that left the tree, kept to be reinstated when the body returns (paper Sec. III-E).

A model that leaves the tree is retired to memory (``model_retired``): at most ``memory_size`` per pair, the least
recently used forgotten first (:func:`least_recently_used`). The memory is asked first when an edge fails
(:mod:`~body_scheme_core.learning.repair`) and challenges the tree's models every step
(:mod:`~body_scheme_core.learning.detection`).
"""

from __future__ import annotations

import math

from ..events import Event, finite_or_none, format_errors
from .tracked import MEMORY

__all__ = ["retire", "least_recently_used"]


def least_recently_used(models, capacity):
    """The models to forget so that at most ``capacity`` remain: least recently used first, then oldest.

    Parameters
    ----------
    models : list of TrackedModel
        The remembered models of one pair.
    capacity : int
        ``memory_size``.

    Returns
    -------
    forgotten : list of TrackedModel
        Ordered by ``(last_used, id)``.
    """
    ordered = sorted(models, key=lambda e: (e.last_used, e.id))
    return ordered[:max(0, len(ordered) - capacity)]


def retire(pool, memory_size, entry, step, events, why):
    """Move a model that left the tree to memory; forget the least recently used beyond ``memory_size``."""
    pool.assign(entry, MEMORY, step)
    pool.monitor.reset_cusum([entry.row])
    same = pool.memory_of_pair(entry.parent, entry.child)
    forgotten = least_recently_used(same, memory_size)
    for e in forgotten:
        pool.remove(e)
    note = f"; forgot {', '.join(e.describe() for e in forgotten)} (least recently used)" if forgotten else ""
    kept = len(same) - len(forgotten)
    mt = mr = math.inf
    if entry.id in pool.tracked:
        st = pool.monitor.stats([entry.row])
        mt, mr = float(st.trans_error[0]), float(st.rot_error[0])
    events.append(Event(step, "model_retired",
                        f"{entry.describe()} retired ({why}); window mean {format_errors(mt, mr)}; memory holds "
                        f"{kept} model(s) of pair {entry.parent}-{entry.child}{note}",
                        parent=entry.parent, child=entry.child, model=entry.describe(),
                        trans_error=finite_or_none(mt), rot_error=finite_or_none(mr)))
