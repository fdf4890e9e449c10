"""Tests of the rigid-joint candidate batch: incremental fits, slots, refit selection and state."""

import json
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from body_scheme_core.errors import InvalidInputError, ModelFileError
from body_scheme_core.models import PrismaticModel, RevoluteModel, RigidBatch, StaticModel
from body_scheme_core.models.revolute import RevoluteForm
from body_scheme_core.transforms import transform_from_rotvec, translational_error

SIGMA = np.array([0.03, math.radians(10)])


def _joint(seed):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    r = rng.normal(size=3) * 0.2
    r -= (r @ u) * u
    return np.concatenate([u, r, rng.normal(size=3) * 0.2, rng.normal(size=3), [1.0]])


def _samples(seed, n, action=0, n_actions=2):
    rng = np.random.default_rng(seed)
    A = rng.uniform(-1.5, 1.5, (n, n_actions))
    Z = RevoluteForm.transforms(_joint(seed)[None], A[None, :, action])[0]
    Z = Z @ transform_from_rotvec(rng.normal(0, SIGMA[1], (n, 3)), rng.normal(0, SIGMA[0], (n, 3)))
    return A, Z


def test_a_slot_learns_what_a_fitted_model_learns():
    """A revolute slot fed sample by sample ends close to RevoluteModel.fit on the same samples (same robust loss)."""
    A, Z = _samples(0, 30)
    batch = RigidBatch(2, 30)
    (slot,) = batch.allocate([("revolute", (0,))])
    for a, z in zip(A, Z, strict=True):
        batch.add_samples([slot], a, z[None], SIGMA[None])
    from_batch = batch.to_model(slot, 1, 2)
    fitted = RevoluteModel(1, 2, (0,), sigma_trans=SIGMA[0], sigma_rot=SIGMA[1]).fit(A, Z)
    test = np.random.default_rng(1).uniform(-1.5, 1.5, (50, 2))
    assert np.mean(translational_error(from_batch.predict(test), fitted.predict(test))) < 0.005
    assert isinstance(from_batch, RevoluteModel) and from_batch.n_samples_ == 30


def test_slots_predict_once_their_form_is_determined():
    """Static slots predict from one sample, prismatic from two, revolute from three; the rest report not ready."""
    A, Z = _samples(2, 3)
    batch = RigidBatch(2, 10)
    slots = batch.allocate([("static", ()), ("prismatic", (0,)), ("revolute", (0,))])
    readiness = []
    for a, z in zip(A, Z, strict=True):
        batch.add_samples(slots, a, np.stack([z] * 3), np.stack([SIGMA] * 3))
        readiness.append(batch.predict(slots, a)[1].tolist())
    assert readiness == [[True, False, False], [True, True, False], [True, True, True]]
    assert isinstance(batch.to_model(slots[0], 1, 2), StaticModel)
    assert isinstance(batch.to_model(slots[1], 1, 2), PrismaticModel)


def test_a_slot_keeps_its_estimate_until_selected_for_a_refit():
    """refit=False appends the sample but keeps the fit; to_model refits a stale slot first."""
    A, Z = _samples(3, 12)
    batch = RigidBatch(2, 20)
    (slot,) = batch.allocate([("revolute", (0,))])
    for a, z in zip(A[:8], Z[:8], strict=True):
        batch.add_samples([slot], a, z[None], SIGMA[None])
    before = batch.predict([slot], A[0])[0].copy()
    for a, z in zip(A[8:], Z[8:], strict=True):
        batch.add_samples([slot], a, z[None], SIGMA[None], refit=[False])
    assert batch.size([slot])[0] == 12
    assert_allclose(batch.predict([slot], A[0])[0], before)
    assert batch.to_model(slot, 1, 2).n_samples_ == 12
    assert not np.allclose(batch.predict([slot], A[0])[0], before)


def test_state_round_trip_continues_identically():
    """A batch restored from its JSON state holds the same slots and continues with identical fits."""
    A, Z = _samples(4, 10)
    batch = RigidBatch(2, 20, fit_scale=True)
    slots = batch.allocate([("revolute", (0,)), ("prismatic", (1,)), ("static", ())])
    for a, z in zip(A[:6], Z[:6], strict=True):
        batch.add_samples(slots, a, np.stack([z] * 3), np.stack([SIGMA] * 3))
    restored = RigidBatch.from_state_dict(json.loads(json.dumps(batch.state_dict())))
    for b in (batch, restored):
        for a, z in zip(A[6:], Z[6:], strict=True):
            b.add_samples(slots, a, np.stack([z] * 3), np.stack([SIGMA] * 3))
    assert_allclose(restored.predict(slots, A[0])[0], batch.predict(slots, A[0])[0], atol=0.0)
    assert restored.fit_scale and restored.to_model(slots[0], 1, 2).fit_scale


def test_slots_are_reused_and_bad_requests_refused():
    """Released slots are reused first; unknown kinds, wrong action counts, repeats and full slots are errors."""
    batch = RigidBatch(2, 1)
    first = batch.allocate([("static", ()), ("revolute", (1,))])
    batch.release([first[0]])
    assert batch.allocate([("prismatic", (0,))]).tolist() == [first[0]]
    for spec in [("spline", (0,)), ("revolute", ()), ("static", (0,)), ("revolute", (2,))]:
        with pytest.raises(InvalidInputError):
            batch.allocate([spec])
    with pytest.raises(InvalidInputError, match="repeat"):
        batch.add_samples([first[1], first[1]], np.zeros(2), np.stack([np.eye(4)] * 2), np.stack([SIGMA] * 2))
    batch.add_samples([first[1]], np.zeros(2), np.eye(4)[None], SIGMA[None])
    with pytest.raises(InvalidInputError, match="capacity"):
        batch.add_samples([first[1]], np.zeros(2), np.eye(4)[None], SIGMA[None])
    with pytest.raises(ModelFileError):
        RigidBatch.from_state_dict({"format": "GPBatch", "version": 1})
