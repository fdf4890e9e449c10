"""Chains whose joints are known, fitted to observations: a specification's chain placed where the parts' markers are
(:func:`register_chain`, when a URDF gives the joints but not the markers' places), and the replacements of a chain
after a change of the body (:func:`chain_replacements`: the same joints fitted again, or one joint stuck). Finding the
joints from scratch is :mod:`~body_scheme_core.learning.chain_search`'s.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from ..errors import BodySchemeError
from ..models import ChainModel, chain_form, increment_jacobian, pose_residuals
from ..rotations import rotation_log, rotvec_matrix
from ..transforms import transform_from_rotvec
from .chain_search import JointScrew, stored_screw

__all__ = ["register_chain", "chain_replacements"]


def register_chain(model, A, Z, sigma, starts=8, rng=0):
    """A chain from the robot's specification (:func:`~body_scheme_core.models.chain_spec.chain_from_engineered`) placed
    where the parts' markers are: ``parent2child = G chain(a) H`` with the parent marker's pose ``G`` on the first
    link and the child marker's ``H`` on the last one fitted to the observations, the specification's joints held.

    What a calibration does first when the markers' places on the links are unknown (a motion-capture body glued on a
    hand, a tracker standing somewhere near the base). ``starts`` orientations of ``G`` are tried (the identity
    first, then random ones from ``rng``); the best fit wins.

    Parameters
    ----------
    model : ChainModel
        Fitted (its parameters: the specification).
    A : ndarray, shape (n, m)
    Z : ndarray, shape (n, 4, 4)
    sigma : array-like, shape (2,) or (n, 2)

    Returns
    -------
    model : ChainModel
        A copy with the screws moved by ``G`` and ``M`` by ``G`` and ``H``, and its covariance with them.
    """
    A, Z = np.asarray(A, dtype=float), np.asarray(Z, dtype=float)
    S = np.broadcast_to(np.asarray(sigma, dtype=float), (len(Z), 2))
    chain = model.predict(A)

    def compose(v):
        return transform_from_rotvec(v[0:3], v[3:6]), transform_from_rotvec(v[6:9], v[9:12])

    def residuals(v):
        G, H = compose(v)
        return np.clip(pose_residuals(G @ chain @ H, Z, S), -1e6, 1e6).ravel()

    rng = np.random.default_rng(rng)
    best = None
    for k in range(starts):
        rotation = np.zeros(3) if k == 0 else rotation_log(rotvec_matrix(rng.normal(size=3) * np.pi)[None])[0]
        # G's translation from the first observation, given the rotation: Z_0 ~ G chain_0.
        G0 = transform_from_rotvec(rotation, np.zeros(3))
        G0[:3, 3] = Z[0, :3, 3] - (G0 @ chain[0])[:3, 3]
        v0 = np.concatenate([rotation, G0[:3, 3], np.zeros(6)])
        result = least_squares(residuals, v0, loss="huber", f_scale=3.0, max_nfev=200)
        if best is None or result.cost < best.cost:
            best = result
    G, H = compose(best.x)
    form = model.form

    def placed(params):
        params = params.copy()
        for kind, at in zip(form.TYPES, form.STORED_AT, strict=True):
            params[at:at + 3] = G[:3, :3] @ params[at:at + 3]
            if kind == "revolute":
                params[at + 3:at + 6] = G[:3, :3] @ params[at + 3:at + 6] + G[:3, 3]
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = rotvec_matrix(params[-3:]), params[-6:-3]
        M = G @ M @ H
        params[-6:-3], params[-3:] = M[:3, 3], rotation_log(M[None, :3, :3])[0]
        return form.canonical(params[None])[0]

    params = placed(model.params_)
    # The covariance moves with the parameters: an increment's coordinates are in each axis' own basis.
    A = increment_jacobian(form, params, lambda d: placed(form.retract(model.params_[None], d[None])[0]),
                           form.N_PARAMS)
    return model.with_params(params, A @ model.param_cov_ @ A.T)


def chain_replacements(model, A, Z, sigma):
    """Replacements of a chain that no longer fits, fitted on the samples since the change: the same chain fitted
    again (a bent link, a moved marker), and for each joint the chain without it (a blocked joint: its motion, at the
    angle it stuck, folded into the joints after it and the reference pose). Returns the fits that succeeded.

    Parameters
    ----------
    model : ChainModel
    A : ndarray, shape (n, m)
    Z : ndarray, shape (n, 4, 4)
    sigma : ndarray, shape (n, 2)
    """
    form = model.form
    hyper = {"sigma_trans": model.sigma_trans, "sigma_rot": model.sigma_rot, "f_scale": model.f_scale}
    out = []
    try:
        out.append(ChainModel(model.parent, model.child, model.actions, model.types, reference=model.reference,
                              couplings=model.couplings, order_evidence=model.order_evidence,
                              inert_actions=model.inert_actions, **hyper)
                   .fit(A, Z, sigma, start=model.params_))
    except (BodySchemeError, np.linalg.LinAlgError, ValueError):
        pass
    k = len(model.actions)
    if k < 2:
        return out
    screws, M = model.screws()
    for i in range(k):
        keep = [j for j in range(k) if j != i]
        couplings = tuple((keep.index(a), keep.index(b)) for a, b in model.couplings if a != i and b != i)
        coefficients = [model.params_[form.COUPLING_STORED_AT + c] for c, (a, b) in enumerate(model.couplings)
                        if a != i and b != i]
        best = None
        # Started as if stuck where the joint was commanded in the middle since the change (the fit moves it).
        for q in (float(np.median(A[:, model.actions[i]]) - model.reference[i]),):
            E = chain_form((model.types[i],)).transforms(
                np.concatenate([stored_screw(model.types[i], screws[i]), np.zeros(6)])[None], np.array([[[q]]]))[0, 0]
            joints = []
            for j in keep:
                screw = screws[j]
                if j > i:  # the joints after the stuck one turn with it
                    if model.types[j] == "revolute":
                        screw = (E[:3, :3] @ screw[0], E[:3, :3] @ screw[1] + E[:3, 3])
                    else:
                        screw = E[:3, :3] @ screw
                joints.append(JointScrew(model.actions[j], model.types[j], screw, 0.0))
            start_M = E @ M
            start = np.concatenate([stored_screw(jt.kind, jt.screw) for jt in joints] + [coefficients]
                                   + [start_M[:3, 3], rotation_log(start_M[None, :3, :3])[0]])
            try:
                fit = ChainModel(model.parent, model.child, tuple(model.actions[j] for j in keep),
                                 tuple(model.types[j] for j in keep), reference=model.reference[keep],
                                 couplings=couplings, order_evidence=model.order_evidence,
                                 inert_actions=model.inert_actions, **hyper
                                 ).fit(A, Z, sigma, start=chain_form(tuple(model.types[j] for j in keep),
                                                                     couplings).canonical(start[None])[0])
            except (BodySchemeError, np.linalg.LinAlgError, ValueError):
                continue
            if best is None or fit.rms_ < best.rms_:
                best = fit
        if best is not None:
            out.append(best)
    return out
