"""Many rigid-joint candidates (static, prismatic, revolute) learning incrementally in stacked arrays.

The rigid counterpart of :class:`~body_scheme_core.models.gp_batch.GPBatch`: each *slot* is one candidate local model of
one form on one action, holding at most ``capacity`` samples (``|D_train|``). Every :meth:`RigidBatch.add_samples` call
appends a sample to each given slot and refits those slots together with :func:`~.rigid_fit.gauss_newton`, grouped by
form, warm-started from their previous estimate. A revolute slot is (re)started from its closed-form estimate when it
reaches :data:`RESTART_SIZES` samples and keeps whichever of the warm and the fresh fit has the lower robust cost, so
an early poor start cannot trap it.

Slots predict only once they hold their form's ``MIN_SAMPLES`` (static 1, prismatic 2, revolute 3); before that
:meth:`RigidBatch.predict` marks them not ready, like an empty GP whose predictions say nothing.
"""

from __future__ import annotations

import numpy as np

from ..errors import BodySchemeError, InvalidInputError, ModelFileError
from ..limits import MAX_ACTION
from ..state_values import boolean, finite_array, integer, listing, number
from ..transforms import check_transform, vector12_from_transform
from .prismatic import PrismaticModel
from .revolute import RevoluteModel
from .rigid_fit import DEFAULT_F_SCALE, covariance, fit_rms, fit_stack, gauss_newton
from .slots import SlotArrays, read_batch_header
from .static import StaticModel

__all__ = ["RigidBatch", "RIGID_CLASSES", "RESTART_SIZES"]

#: The rigid model classes a batch holds, by kind.
RIGID_CLASSES = {cls.kind: cls for cls in (StaticModel, PrismaticModel, RevoluteModel)}
_KINDS = tuple(RIGID_CLASSES)
#: Training-set sizes at which a revolute slot also tries a fresh closed-form start.
RESTART_SIZES = (3, 5, 8, 12)
#: Iterations (Gauss-Newton steps, or re-weightings of a linear form) after each new sample, warm-started, and from
#: a fresh start.
_WARM_ITERATIONS = 1
_FRESH_ITERATIONS = 3
_STORED = max(cls.form.N_STORED for cls in RIGID_CLASSES.values())


class RigidBatch(SlotArrays):
    """Incremental rigid-joint candidates ("slots") in stacked arrays.

    Parameters
    ----------
    n_actions : int
        Length m of the full action vectors.
    capacity : int
        Largest number of training samples per slot.
    f_scale : float
        Huber threshold of the fits, in sigmas.
    fit_scale : bool
        Whether joint candidates fit the scale between action and joint motion (see the model classes).
    """

    def __init__(self, n_actions, capacity, f_scale=DEFAULT_F_SCALE, fit_scale=False):
        for name, value, least in [("n_actions", n_actions, 0), ("capacity", capacity, 1)]:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise InvalidInputError(f"{name} must be an integer >= {least}, got {value!r}")
        self.n_actions = int(n_actions)
        self.capacity = int(capacity)
        self.f_scale = float(f_scale)
        self.fit_scale = bool(fit_scale)
        self._forms = [RIGID_CLASSES[kind].form_for(self.fit_scale) for kind in _KINDS]
        self._min_samples = np.array([form.MIN_SAMPLES for form in self._forms])
        self._init_slots()
        self._kind = np.zeros(0, dtype=int)
        self._action = np.zeros(0, dtype=int)
        self._n = np.zeros(0, dtype=int)
        self._x = np.zeros((0, self.capacity))
        self._Z = np.zeros((0, self.capacity, 4, 4))
        self._S = np.ones((0, self.capacity, 2))
        self._params = np.zeros((0, _STORED))
        self._cost = np.zeros(0)
        self._fit_n = np.zeros(0, dtype=int)  # training-set size at the last fit

    # ------------------------------------------------------------------ slots
    def slot_kind(self, slot):
        """Kind (``"static"``, ``"prismatic"``, ``"revolute"``) of one allocated slot."""
        return _KINDS[self._kind[int(self._check_slots([slot])[0])]]

    def slot_actions(self, slot):
        """Action indices (tuple) of one allocated slot."""
        slot = int(self._check_slots([slot])[0])
        return () if self._action[slot] < 0 else (int(self._action[slot]),)

    def _slot_fills(self):
        return {"_kind": 0, "_action": -1, "_n": 0, "_x": 0.0, "_Z": np.eye(4), "_S": 1.0, "_params": 0.0,
                "_cost": 0.0, "_fit_n": 0}

    def _check_spec(self, spec):
        try:
            kind, actions = spec
            actions = tuple(int(a) for a in actions)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"a slot is (kind, actions), got {spec!r}") from exc
        if kind not in RIGID_CLASSES:
            raise InvalidInputError(f"unknown rigid kind {kind!r}; known: {list(RIGID_CLASSES)}")
        if len(actions) != (0 if kind == "static" else 1) or any(not 0 <= a < self.n_actions for a in actions):
            raise InvalidInputError(f"a {kind} slot needs {0 if kind == 'static' else 1} action index in "
                                    f"[0, {self.n_actions}), got {actions}")
        return _KINDS.index(kind), (actions[0] if actions else -1)

    def allocate(self, specs):
        """Allocate empty slots, one per ``(kind, actions)``; returns their indices (k,), reusing free ones first."""
        checked = [self._check_spec(spec) for spec in specs]
        slots = self._take_slots(len(checked))
        for slot, (kind, action) in zip(slots, checked, strict=True):
            self._kind[slot] = kind
            self._action[slot] = action
        return slots

    def ready(self, slots):
        """Whether each slot holds enough samples to be fitted (its form's ``MIN_SAMPLES``), shape (k,)."""
        slots = self._check_slots(slots)
        return self._n[slots] >= self._min_samples[self._kind[slots]]

    def fitted(self, slots):
        """Whether each slot has an estimate to predict with, shape (k,)."""
        slots = self._check_slots(slots)
        return self._fit_n[slots] >= self._min_samples[self._kind[slots]]

    def _check_a(self, a):
        a = np.asarray(a, dtype=float).reshape(-1)
        if a.shape != (self.n_actions,) or not np.all(np.isfinite(a)):
            raise InvalidInputError(f"a must be one finite action vector of shape ({self.n_actions},), got {a.shape}")
        return a

    def _values(self, slots, a):
        """Each slot's own action value in ``a`` (0 for static slots), shape (k,)."""
        padded = np.append(a, 0.0)  # static slots (action -1) read the appended 0
        return padded[np.where(self._action[slots] >= 0, self._action[slots], self.n_actions)]

    # ------------------------------------------------------------------ inference and learning
    def predict(self, slots, a):
        """Predict every slot at one full action vector.

        Returns
        -------
        Z : ndarray, shape (k, 4, 4)
            Identity where a slot is not ready.
        ready : ndarray of bool, shape (k,)
            Whether the slot has an estimate (:meth:`fitted`).
        """
        slots = self._check_slots(slots)
        a = self._check_a(a)
        ready = self.fitted(slots)
        Z = np.broadcast_to(np.eye(4), (slots.size, 4, 4)).copy()
        x = self._values(slots, a)
        for code in range(len(_KINDS)):
            group = np.flatnonzero((self._kind[slots] == code) & ready)
            if group.size:
                form = self._forms[code]
                Z[group] = form.transforms(self._params[slots[group], :form.N_STORED], x[group, None])[:, 0]
        return Z, ready

    def add_samples(self, slots, a, Z, sigma, refit=None):
        """Append one sample to each slot and refit them (or those selected by ``refit``).

        Parameters
        ----------
        slots : array-like of int, shape (k,)
            Distinct allocated slots, none of them full.
        a : array-like, shape (m,)
        Z : array-like, shape (k, 4, 4)
            Observed ``parent2child`` per slot.
        sigma : array-like, shape (k, 2)
            Per-axis noise std of each slot's sample (trans m, rot rad).
        refit : array-like of bool, shape (k,), optional
            Which slots to refit now (default: all). The others keep their estimate, which stays a fair,
            prequential predictor (trained on a subset of the past); they are refit when selected later or by
            :meth:`to_model`. Lets a caller spend the fitting effort on promising candidates.
        """
        slots = self._check_slots(slots)
        if np.unique(slots).size != slots.size:
            raise InvalidInputError("slots must not repeat in one update")
        a = self._check_a(a)
        Z = check_transform(Z, name="Z", tolerance=1e-4)
        sigma = np.asarray(sigma, dtype=float)
        if Z.shape != (slots.size, 4, 4) or sigma.shape != (slots.size, 2):
            raise InvalidInputError(f"Z must be ({slots.size}, 4, 4) and sigma ({slots.size}, 2), got {Z.shape}, "
                                    f"{sigma.shape}")
        if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
            raise InvalidInputError("sigma must be finite and > 0")
        full = self._n[slots] >= self.capacity
        if np.any(full):
            raise InvalidInputError(f"slots already hold capacity={self.capacity} samples: {slots[full].tolist()}")
        n = self._n[slots]
        self._x[slots, n] = self._values(slots, a)
        self._Z[slots, n] = Z
        self._S[slots, n] = sigma
        self._n[slots] = n + 1
        do = self.ready(slots)
        if refit is not None:
            do &= np.asarray(refit, dtype=bool).reshape(slots.shape)
        self._refit(slots[do])

    def _refit(self, slots):
        for code in range(len(_KINDS)):
            group = slots[self._kind[slots] == code]
            if group.size == 0:
                continue
            form = self._forms[code]
            n_max = int(self._n[group].max())
            x, Z, S = self._x[group, :n_max], self._Z[group, :n_max], self._S[group, :n_max]
            mask = np.arange(n_max) < self._n[group, None]
            q = form.N_STORED
            # A slot that was never fitted starts fresh; a revolute slot also restarts when it crossed a restart size
            # since its last fit.
            fitted = self._fit_n[group]
            fresh = fitted < form.MIN_SAMPLES
            if not getattr(form, "CLOSED_FORM_CANDIDATE", False):
                sizes = np.asarray(RESTART_SIZES)
                fresh |= np.any((fitted[:, None] < sizes) & (self._n[group, None] >= sizes), axis=1)
            warm = self._params[group, :q]
            if getattr(form, "CLOSED_FORM_CANDIDATE", False):
                # The weighted least-squares closed form; the robust loss (and, for a unit axis, the exact
                # constrained fit) is applied when the candidate becomes a model (to_model).
                self._params[group, :q] = form.initial(x, Z, S, mask)
                self._fit_n[group] = self._n[group]
                continue
            params, cost = warm.copy(), self._cost[group].copy()
            keep = np.flatnonzero(~fresh)
            if keep.size:
                params[keep], cost[keep] = fit_stack(form, warm[keep], x[keep], Z[keep], S[keep], mask[keep],
                                                     _WARM_ITERATIONS, self.f_scale)
            new = np.flatnonzero(fresh)
            if new.size:
                xf, Zf, Sf, mf = x[new], Z[new], S[new], mask[new]
                params[new], cost[new] = fit_stack(form, form.initial(xf, Zf, Sf, mf), xf, Zf, Sf, mf,
                                                   _FRESH_ITERATIONS, self.f_scale)
                # At a restart size the warm estimate also continues; the better of the two is kept.
                retry = fitted[new] >= form.MIN_SAMPLES
                if np.any(retry):
                    idx = new[retry]
                    w_params, w_cost = fit_stack(form, warm[idx], x[idx], Z[idx], S[idx], mask[idx],
                                                 _WARM_ITERATIONS, self.f_scale)
                    take = w_cost < cost[idx]
                    params[idx[take]], cost[idx[take]] = w_params[take], w_cost[take]
            self._params[group, :q] = params
            self._cost[group] = cost
            self._fit_n[group] = self._n[group]

    # ------------------------------------------------------------------ conversion
    def to_model(self, slot, parent, child):
        """The slot's fitted model (:class:`StaticModel`, ... with covariance), unfitted if it is not ready."""
        slot = int(self._check_slots([slot])[0])
        cls = RIGID_CLASSES[_KINDS[self._kind[slot]]]
        options = {} if cls.kind == "static" else {"fit_scale": self.fit_scale}
        model = cls(parent, child, self.slot_actions(slot), f_scale=self.f_scale, **options)
        if not self.ready([slot])[0]:
            return model
        if self._fit_n[slot] < self._n[slot]:
            self._refit(np.array([slot]))
        n = int(self._n[slot])
        form = model.form
        params = self._params[slot, :form.N_STORED][None].copy()
        x, Z, S = self._x[slot, None, :n], self._Z[slot, None, :n], self._S[slot, None, :n]
        mask = np.ones((1, n), dtype=bool)
        if getattr(form, "CLOSED_FORM_CANDIDATE", False):
            params, _ = fit_stack(form, params, x, Z, S, mask, 3, self.f_scale)  # robust (and exact) fit
        _, cost, JtWJ = gauss_newton(form, params, x, Z, S, mask, 0, self.f_scale)
        return model._set_fit(params[0], covariance(JtWJ, cost, 6 * n, form.N_PARAMS)[0], n,
                              fit_rms(cost[0], n))

    def training_data(self, slot):
        """The slot's samples: action values (n,), ``Z`` (n, 4, 4) and sigmas (n, 2)."""
        slot = int(self._check_slots([slot])[0])
        n = int(self._n[slot])
        return self._x[slot, :n].copy(), self._Z[slot, :n].copy(), self._S[slot, :n].copy()

    # ------------------------------------------------------------------ state
    def state_dict(self):
        """JSON-serialisable state: settings and, per storage slot, ``None`` (free) or its kind, data and fit."""
        slots = []
        for slot in range(self._storage):
            if not self._allocated[slot]:
                slots.append(None)
                continue
            n = int(self._n[slot])
            slots.append({"kind": _KINDS[self._kind[slot]], "actions": list(self.slot_actions(slot)),
                          "x": self._x[slot, :n].tolist(), "Z": vector12_from_transform(self._Z[slot, :n]).tolist(),
                          "sigma": self._S[slot, :n].tolist(), "params": self._params[slot].tolist(),
                          "cost": float(self._cost[slot]), "fit_n": int(self._fit_n[slot])})
        return {"format": "RigidBatch", "version": 1, "n_actions": self.n_actions, "capacity": self.capacity,
                "f_scale": self.f_scale, "fit_scale": self.fit_scale, "slots": slots}

    @classmethod
    def from_state_dict(cls, data):
        """Rebuild from :meth:`state_dict` output with the same slot indices and fits (no refitting)."""
        try:
            n_actions, capacity, entries = read_batch_header(data, "RigidBatch")
            batch = cls(n_actions, capacity, number(data["f_scale"], "RigidBatch f_scale", above=0.0),
                        boolean(data["fit_scale"], "RigidBatch fit_scale"))
            batch._grow(len(entries))
            for slot, entry in enumerate(entries):
                if entry is None:
                    continue
                code, action = batch._check_spec((entry["kind"], entry["actions"]))
                n = len(listing(entry["x"], f"RigidBatch slot {slot} x"))
                if n > batch.capacity:
                    raise ModelFileError(f"slot {slot}: {n} samples exceed the capacity {batch.capacity}")
                x = finite_array(entry["x"], (n,), f"RigidBatch slot {slot} x")
                Z = finite_array(entry["Z"], (n, 12), f"RigidBatch slot {slot} Z")
                S = finite_array(entry["sigma"], (n, 2), f"RigidBatch slot {slot} sigma")
                params = finite_array(entry["params"], (_STORED,), f"RigidBatch slot {slot} params")
                if np.any(S <= 0) or np.any(np.abs(x) > MAX_ACTION):
                    raise ModelFileError(f"slot {slot}: sigmas <= 0 or actions beyond {MAX_ACTION:g}")
                batch._allocated[slot] = True
                batch._kind[slot], batch._action[slot], batch._n[slot] = code, action, n
                batch._x[slot, :n] = x
                # Rebuilt entry by entry (no re-projection), so a restored batch continues bit-identically.
                T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
                T[:, :3, :3], T[:, :3, 3] = Z[:, :9].reshape(n, 3, 3), Z[:, 9:]
                batch._Z[slot, :n] = check_transform(T, name="Z", tolerance=1e-4)
                batch._S[slot, :n] = S
                batch._params[slot] = params
                batch._cost[slot] = number(entry["cost"], f"RigidBatch slot {slot} cost", 0.0)
                batch._fit_n[slot] = integer(entry["fit_n"], f"RigidBatch slot {slot} fit_n", 0, n)
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, BodySchemeError) as exc:
            raise ModelFileError(f"cannot read RigidBatch state: {exc}") from exc
        return batch
