"""Slots: many models of one kind as rows of stacked arrays, the storage of the batched engines.

:class:`~.gp_batch.GPBatch` and :class:`~.rigid_batch.RigidBatch` hold hundreds of candidate local models each, one
*slot* (row) per model, so that a step updates all of them with a few numpy calls. :class:`SlotArrays` is what they
share: which slots are allocated, growth by doubling when none is free, reuse of released slots (lowest first, reset
to their empty values) and the validation of slot indices.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError, ModelFileError
from ..limits import MAX_ACTIONS, MAX_WINDOW
from ..state_values import integer, listing, mapping

__all__ = ["SlotArrays", "read_batch_header"]


class SlotArrays:
    """Base of the batched engines (see the module docstring).

    A subclass creates its per-slot arrays with zero rows, calls :meth:`_init_slots`, and names them with their
    empty values in :meth:`_slot_fills`; each must have one row per slot and the sample count ``_n``.
    """

    def _init_slots(self):
        self._storage = 0
        self._allocated = np.zeros(0, dtype=bool)

    def _slot_fills(self):
        """``{attribute name: value of an empty slot}`` (broadcast over a row) of every per-slot array."""
        raise NotImplementedError

    @property
    def n_allocated(self):
        """Number of allocated slots."""
        return int(np.count_nonzero(self._allocated))

    def is_allocated(self, slot):
        """Whether ``slot`` (an int) is an allocated slot."""
        return 0 <= slot < len(self._allocated) and bool(self._allocated[slot])

    @property
    def allocated_slots(self):
        """Allocated slot indices, ascending."""
        return np.flatnonzero(self._allocated)

    def size(self, slots):
        """Number of training samples of each slot, shape (k,)."""
        return self._n[self._check_slots(slots)]  # an index array: a copy

    def _grow(self, storage):
        """Grow every per-slot array to ``storage`` rows of empty slots."""
        extra = storage - self._storage
        for name, fill in self._slot_fills().items():
            array = getattr(self, name)
            rows = np.broadcast_to(np.asarray(fill, dtype=array.dtype), (extra,) + array.shape[1:])
            setattr(self, name, np.concatenate([array, rows]))
        self._allocated = np.concatenate([self._allocated, np.zeros(extra, dtype=bool)])
        self._storage = storage

    def _reset(self, slots):
        for name, fill in self._slot_fills().items():
            getattr(self, name)[slots] = fill

    def _take_slots(self, k):
        """``k`` free slots, empty and marked allocated; released ones first (lowest first), then new storage."""
        free = np.flatnonzero(~self._allocated)
        if free.size < k:
            self._grow(max(2 * self._storage, self._storage + k - free.size, 16))
            free = np.flatnonzero(~self._allocated)
        slots = free[:k]
        self._reset(slots)
        self._allocated[slots] = True
        return slots

    def release(self, slots):
        """Free slots for reuse; their data are discarded."""
        slots = self._check_slots(slots)
        self._reset(slots)
        self._allocated[slots] = False
        return slots

    def snapshot(self):
        """What :meth:`restore` needs to undo any change from now on: the attributes and a copy of the allocated
        slots' rows (free slots are reset when they are taken, so their contents do not matter; after racing most of
        the storage is free, and copying it whole was a large part of a bootstrapping step)."""
        rows = self.allocated_slots  # an index array: indexing with it copies the rows
        kept = {name: getattr(self, name)[rows] for name in self._slot_fills()} if rows.size else {}
        return dict(vars(self)), rows, kept, self._allocated.copy()

    def restore(self, saved):
        """Undo every change since :meth:`snapshot` returned ``saved``."""
        attributes, rows, kept, allocated = saved
        vars(self).update(attributes)  # the arrays of then (a step that grew the storage made new ones)
        for name, values in kept.items():
            getattr(self, name)[rows] = values
        self._allocated = allocated

    def _check_slots(self, slots, unique=False):
        """Slot indices as an intp array; raise unless each is allocated (and, with ``unique``, none repeats)."""
        slots = np.atleast_1d(np.asarray(slots))
        if slots.ndim != 1 or not (np.issubdtype(slots.dtype, np.integer) or slots.size == 0):
            raise InvalidInputError(f"slots must be a 1-d array of ints, got shape {slots.shape} dtype {slots.dtype}")
        slots = slots.astype(np.intp, copy=False)
        if slots.size and (slots.min() < 0 or slots.max() >= self._storage):
            raise InvalidInputError(f"slot index out of range [0, {self._storage}): {slots.min()}..{slots.max()}")
        if not np.all(self._allocated[slots]):
            raise InvalidInputError(f"slots not allocated: {slots[~self._allocated[slots]].tolist()}")
        if unique and np.unique(slots).size != slots.size:
            raise InvalidInputError("slots must not repeat in one update")
        return slots


def read_batch_header(data, fmt):
    """``(n_actions, capacity, slots)`` of a batch's state dict of format ``fmt``, within the sizes a learner uses
    (checked before anything is allocated)."""
    data = mapping(data, f"{fmt} state")
    if data.get("format") != fmt or data.get("version") != 1:
        raise ModelFileError(f"not a {fmt} state (format {data.get('format')!r:.40}, version "
                             f"{data.get('version')!r:.40})")
    return (integer(data["n_actions"], f"{fmt} n_actions", 0, MAX_ACTIONS),
            integer(data["capacity"], f"{fmt} capacity", 1, MAX_WINDOW), listing(data["slots"], f"{fmt} slots"))
