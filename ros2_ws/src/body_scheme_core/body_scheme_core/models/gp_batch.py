"""The batched incremental engine in which GP candidates learn: many GP local models in stacked arrays.

Bootstrapping and every replacement start hundreds of GP candidates (one per pair of parts and action set), each
trained on at most ``train_window`` samples and tested prequentially. :class:`GPBatch` holds them as *slots* of
padded arrays and updates all of them with a handful of numpy calls per step; :meth:`GPBatch.to_model` turns a
slot into a :class:`~body_scheme_core.models.gp.GPModel` fitted on exactly its data. The kernel and the
hyperparameters are those of :mod:`~body_scheme_core.models.gp_kernel`.
"""

from __future__ import annotations

import numpy as np

from ..errors import BodySchemeError, InvalidInputError, ModelFileError
from ..limits import MAX_ACTIONS
from ..rotations import project_to_rotation_batch
from ..state_values import integer, mapping, number
from ..transforms import check_transform, vector12_from_transform
from .gp import GPModel, _training_arrays
from .gp_kernel import ROT_OUTPUTS, TRANS_OUTPUTS, GPHyperparameters, _clamp_variance, summarise_std
from .slots import SlotArrays, read_batch_header

__all__ = ["GPBatch"]


class GPBatch(SlotArrays):
    """Many incremental GP local models ("slots") in stacked arrays, updated together without Python loops.

    Each slot is a GP of :class:`GPModel` over its own action indices, holding at most ``capacity`` samples. The
    inverse ``(K + r^2 I)^-1`` of every slot is kept and extended by one row and column per sample with the block
    (Schur complement) formula, O(n^2) per slot. Arrays are padded to ``capacity`` samples and ``max_dim`` inputs;
    padded inputs are 0 in both training and query inputs, so they do not change distances.

    Parameters
    ----------
    n_actions : int
        Length m of the full action vectors.
    capacity : int
        Largest number of training samples per slot (the paper's ``|D_train|``).
    max_dim : int
        Largest number of actions a slot may depend on.
    length_scale, signal_std_trans, signal_std_rot, noise_std_trans, noise_std_rot : float
        See :class:`GPHyperparameters`.
    """

    def __init__(self, n_actions, capacity, max_dim, length_scale, signal_std_trans, signal_std_rot,
                 noise_std_trans, noise_std_rot):
        for name, value in [("n_actions", n_actions), ("capacity", capacity), ("max_dim", max_dim)]:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise InvalidInputError(f"{name} must be an integer >= 0, got {value!r}")
        if capacity < 1:
            raise InvalidInputError(f"capacity must be >= 1, got {capacity}")
        self.n_actions = int(n_actions)
        self.capacity = int(capacity)
        self.max_dim = int(max_dim)
        self.hyperparameters = GPHyperparameters(length_scale, signal_std_trans, signal_std_rot, noise_std_trans,
                                                 noise_std_rot)
        hp = self.hyperparameters
        self._ratios2 = hp.ratios**2
        self._group = hp.output_group
        self._signal_std = hp.signal_std
        self._n_groups = len(self._ratios2)
        self._gamma = -0.5 / hp.length_scale**2
        self._init_slots()
        self._dim = np.zeros(0, dtype=int)
        self._n = np.zeros(0, dtype=int)
        # Padded action indices point at an extra 0 appended to the action vector.
        self._actions = np.zeros((0, self.max_dim), dtype=int)
        # Inputs component-major (slot, dim, sample): distances then run over contiguous rows of samples.
        self._X = np.zeros((0, self.max_dim, self.capacity))
        self._Y = np.zeros((0, self.capacity, 12))
        self._Ysum = np.zeros((0, 12))
        self._Kinv = np.zeros((0, self._n_groups, self.capacity, self.capacity))
        self._version = 0
        self._cache = None

    @classmethod
    def from_config(cls, n_actions, config, max_dim=None):
        """Batch with ``capacity = config.train_window`` and ``max_dim = config.max_complexity`` unless given."""
        max_dim = config.max_complexity if max_dim is None else max_dim
        return cls(n_actions, config.train_window, max_dim, **GPHyperparameters.from_config(config).to_dict())

    # ------------------------------------------------------------------ slots

    def slot_actions(self, slot):
        """Action indices (tuple) of one allocated slot."""
        slot = int(self._check_slots([slot])[0])
        return tuple(int(a) for a in self._actions[slot, :self._dim[slot]])

    def _slot_fills(self):
        # Padded action indices point at an extra 0 appended to the action vector.
        return {"_dim": 0, "_n": 0, "_actions": self.n_actions, "_X": 0.0, "_Y": 0.0, "_Ysum": 0.0, "_Kinv": 0.0}

    def _check_slot_actions(self, actions):
        try:
            actions = tuple(int(a) for a in actions)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"actions must be a tuple of ints, got {actions!r}") from exc
        if len(actions) > self.max_dim:
            raise InvalidInputError(f"a slot may depend on at most max_dim={self.max_dim} actions, got {actions}")
        if len(set(actions)) != len(actions) or any(not 0 <= a < self.n_actions for a in actions):
            raise InvalidInputError(f"actions must be distinct indices in [0, {self.n_actions}), got {actions}")
        return actions

    def _assign(self, slot, actions):
        """Give an empty allocated slot its action indices."""
        self._actions[slot, :len(actions)] = actions
        self._dim[slot] = len(actions)

    def allocate(self, actions_list):
        """Allocate empty GPs, one per tuple of action indices; returns their slot indices, shape (k,).

        Released slots are reused, lowest first; storage grows (doubling) when none is free.
        """
        checked = [self._check_slot_actions(actions) for actions in actions_list]
        slots = self._take_slots(len(checked))
        for slot, actions in zip(slots, checked, strict=True):
            self._assign(slot, actions)
        self._version += 1
        return slots

    def release(self, slots):
        """Free slots for reuse; their data are discarded."""
        slots = super().release(slots)
        self._version += 1
        return slots

    def _check_a(self, a):
        a = np.asarray(a, dtype=float)
        if a.ndim == 2 and a.shape[0] == 1:
            a = a[0]
        if a.shape != (self.n_actions,):
            raise InvalidInputError(f"a must be one action vector of shape ({self.n_actions},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InvalidInputError("a contains NaN or inf")
        return a

    @staticmethod
    def _index(slots):
        """A slice when the slots are consecutive (views, no copies), else the index array."""
        if slots.size and slots[-1] - slots[0] == slots.size - 1 and np.all(np.diff(slots) == 1):
            return slice(int(slots[0]), int(slots[-1]) + 1)
        return slots

    # -------------------------------------------------------------- inference

    def _kernel_solve(self, idx, x, ne):
        """Kernel vector to the first ``ne`` training inputs (k, ne) and ``Kinv k`` per ratio (k, G, ne)."""
        X = self._X[idx, :, :ne]
        sqdist = np.zeros((x.shape[0], ne))
        for d in range(self.max_dim):  # a loop over at most max_dim input dimensions, not over slots
            diff = X[:, d] - x[:, d, None]
            sqdist += diff * diff
        kb = np.exp(self._gamma * sqdist)
        v = (self._Kinv[idx, :, :ne, :ne] @ kb[:, None, :, None])[..., 0]
        return kb, v

    def _inputs(self, slots, a):
        return np.append(a, 0.0)[self._actions[slots]]

    def predict(self, slots, a, return_std=False):
        """Predict every slot at one full action vector.

        Parameters
        ----------
        slots : array-like of int, shape (k,)
        a : array-like, shape (m,)
            One action vector shared by all slots; each slot reads its own action indices.
        return_std : bool

        Returns
        -------
        Z : ndarray, shape (k, 4, 4)
            Identity for empty slots.
        std : ndarray, shape (k, 2)
            Only if ``return_std``: latent per-axis std ``[trans m, rot rad]``; ``inf`` for empty slots.
        """
        slots = self._check_slots(slots)
        a = self._check_a(a)
        k = slots.size
        idx = self._index(slots)
        n = self._n[idx]
        ne = int(n.max()) if k else 0
        x = self._inputs(idx, a)
        kb, v = self._kernel_solve(idx, x, ne)
        self._cache = (self._version, slots.copy(), a.tobytes(), kb, v)
        ybar = self._Ysum[idx] / np.maximum(n, 1)[:, None]
        # mu = ybar + v^T (Y - ybar) = ybar (1 - sum(v)) + v^T Y; Kinv is zero-padded, so is v.
        vY = v @ self._Y[idx, :ne]  # (k, G, 12)
        vsum = v.sum(axis=2)
        if self._n_groups == 1:
            mean = vY[:, 0] + ybar * (1.0 - vsum)
        else:
            mean = vY[:, self._group, np.arange(12)] + ybar * (1.0 - vsum[:, self._group])
        empty = n == 0
        mean[empty] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
        Z = np.zeros((k, 4, 4))
        Z[:, :3, :3] = project_to_rotation_batch(mean[:, ROT_OUTPUTS].reshape(k, 3, 3))
        Z[:, :3, 3] = mean[:, TRANS_OUTPUTS]
        Z[:, 3, 3] = 1.0
        if not return_std:
            return Z
        var = _clamp_variance(1.0 - np.einsum("sn,sgn->sg", kb, v))
        std = summarise_std(self._signal_std * np.sqrt(var[:, self._group]))
        std[empty] = np.inf
        return Z, std

    def add_samples(self, slots, a, Z):
        """Append one sample ``(a, Z)`` to each slot.

        Parameters
        ----------
        slots : array-like of int, shape (k,)
            Distinct allocated slots, none of them full (filter with :meth:`size`).
        a : array-like, shape (m,)
            One action vector shared by all slots.
        Z : array-like, shape (k, 4, 4) or (4, 4)
            Observed ``parent2child`` per slot, or one transform for all.
        """
        slots = self._check_slots(slots, unique=True)
        a = self._check_a(a)
        Z = check_transform(Z, name="Z", tolerance=1e-4)
        if Z.shape == (4, 4):
            Z = np.broadcast_to(Z, (slots.size, 4, 4))
        if Z.shape != (slots.size, 4, 4):
            raise InvalidInputError(f"Z must have shape (4, 4) or ({slots.size}, 4, 4), got {Z.shape}")
        full = self._n[slots] >= self.capacity
        if np.any(full):
            raise InvalidInputError(f"slots already hold capacity={self.capacity} samples: {slots[full].tolist()}")
        if slots.size == 0:
            return
        idx = self._index(slots)
        self._append(slots, idx, self._inputs(idx, a), vector12_from_transform(Z), self._cached_solve(slots, a))

    def _cached_solve(self, slots, a):
        """Kernel vectors and solves of the last ``predict`` if it saw this state, this ``a`` and these slots."""
        cache = self._cache
        if cache is None or cache[0] != self._version or cache[2] != a.tobytes():
            return None
        cached_slots, kb, v = cache[1], cache[3], cache[4]
        if np.array_equal(cached_slots, slots):
            return kb, v
        # The usual caller predicts all candidates, then adds to those not yet full: reuse their rows.
        position = np.full(self._storage, -1)
        position[cached_slots] = np.arange(cached_slots.size)
        rows = position[slots]
        if np.any(rows < 0):
            return None
        ne = int(self._n[slots].max())
        # Entries of v beyond a slot's own size are exactly 0 (zero-padded inverse), so truncating is exact.
        return kb[rows, :ne], v[rows, :, :ne]

    def _append(self, slots, idx, x, y, cached=None):
        """Extend each slot's inverse by one sample: inputs ``x`` (k, max_dim), targets ``y`` (k, 12)."""
        n = self._n[idx]
        ne = int(n.max())
        kb, u = cached if cached is not None else self._kernel_solve(idx, x, ne)
        # Schur complement of the new diagonal entry: the predictive variance of the new noisy sample in unit
        # kernel scale, >= r^2 in exact arithmetic.
        schur = 1.0 + self._ratios2 - np.einsum("sn,sgn->sg", kb, u)
        if np.any(schur <= 1e-9 * self._ratios2):
            bad = slots[np.any(schur <= 1e-9 * self._ratios2, axis=1)]
            raise BodySchemeError(
                f"incremental GP update lost positive definiteness in slots {bad.tolist()} (Schur complement "
                f"{schur.min():.3g}); the noise-to-signal ratio {np.sqrt(self._ratios2).tolist()} is too small for "
                "double precision: increase the noise std relative to the signal std.")
        # The block inverse [[A^-1 + u u^T / s, -u / s], [-u^T / s, 1 / s]] is A^-1 (zero-padded) plus one rank-1
        # term (1 / s) [u; -1] [u; -1]^T, so a single broadcast update over contiguous rows covers all slots.
        k = n.shape[0]
        ne1 = ne + 1
        ext = np.zeros((k, self._n_groups, self.capacity))
        ext[..., :ne] = u
        ext[np.arange(k), :, n] = -1.0
        update = (ext[..., :ne1, None] / schur[:, :, None, None]) * ext[..., None, :]
        if isinstance(idx, slice):
            self._Kinv[idx, :, :ne1] += update
        else:
            self._Kinv[idx, :, :ne1] = self._Kinv[idx, :, :ne1] + update
        self._X[slots, :, n] = x
        self._Y[slots, n] = y
        self._Ysum[slots] += y
        self._n[slots] = n + 1
        self._version += 1
        self._cache = None

    # ------------------------------------------------------------ conversion

    def to_model(self, slot, parent, child):
        """A :class:`GPModel` fitted on exactly this slot's data (unfitted if the slot is empty)."""
        slot = int(self._check_slots([slot])[0])
        actions = tuple(int(a) for a in self._actions[slot, :self._dim[slot]])
        model = GPModel(parent, child, actions, **self.hyperparameters.to_dict())
        n = self._n[slot]
        if n:
            model._fit_components(self._X[slot, :len(actions), :n].T.copy(), self._Y[slot, :n].copy())
        return model

    def state_dict(self):
        """JSON-serialisable state: settings and, per storage slot, ``None`` (free) or its actions and data."""
        slots = []
        for slot in range(self._storage):
            if not self._allocated[slot]:
                slots.append(None)
                continue
            n, d = int(self._n[slot]), int(self._dim[slot])
            slots.append({"actions": self._actions[slot, :d].tolist(), "X": self._X[slot, :d, :n].T.tolist(),
                          "Y": self._Y[slot, :n].tolist()})
        return {"format": "GPBatch", "version": 1, "n_actions": self.n_actions, "capacity": self.capacity,
                "max_dim": self.max_dim, "hyperparameters": self.hyperparameters.to_dict(), "slots": slots}

    @classmethod
    def from_state_dict(cls, data):
        """Rebuild a batch from :meth:`state_dict` output, replaying the samples in order; same slot indices."""
        try:
            n_actions, capacity, entries = read_batch_header(data, "GPBatch")
            batch = cls(n_actions, capacity, integer(data["max_dim"], "GPBatch max_dim", 0, MAX_ACTIONS),
                        **{k: number(v, f"GPBatch {k}", above=0.0)
                           for k, v in mapping(data["hyperparameters"], "GPBatch hyperparameters").items()})
            batch._grow(len(entries))
            X = np.zeros((len(entries), batch.capacity, batch.max_dim))
            Y = np.zeros((len(entries), batch.capacity, 12))
            sizes = np.zeros(len(entries), dtype=int)
            for slot, entry in enumerate(entries):
                if entry is None:
                    continue
                actions = tuple(integer(a, "GPBatch slot action", 0, n_actions - 1) for a in entry["actions"])
                d = len(actions)
                if d > batch.max_dim:
                    raise ModelFileError(f"slot {slot}: {d} actions exceed max_dim {batch.max_dim}")
                Xs, Ys = _training_arrays(entry["X"], entry["Y"], d)
                n = Xs.shape[0]
                if Ys.shape != (n, 12) or n > batch.capacity:
                    raise ModelFileError(f"slot {slot}: X {Xs.shape} and Y {Ys.shape} do not match or exceed "
                                         f"capacity {batch.capacity}")
                batch._assign(slot, batch._check_slot_actions(actions))
                batch._allocated[slot] = True
                X[slot, :n, :d] = Xs
                Y[slot, :n] = Ys
                sizes[slot] = n
            # Replaying sample by sample repeats the incremental updates that built the saved batch.
            for k in range(int(sizes.max()) if sizes.size else 0):
                slots = np.flatnonzero(sizes > k)
                batch._append(slots, slots, X[slots, k], Y[slots, k])
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, BodySchemeError) as exc:
            raise ModelFileError(f"cannot read GPBatch state: {exc}") from exc
        return batch
