"""Batched prediction: many linear Koopman models on many episodes at once.

One implementation serves a single prediction and a regularization sweep
(one model per alpha, every validation episode). When the state is re-lifted
at every step only the rows of ``A`` and ``B`` that produce the passthrough
(controller) states and the original plant states are needed: the rest of
the lifted state is recomputed from the predicted history. On the
QUBE-Servo that is 4 rows of 57.
"""

from __future__ import annotations

import numpy as np

from qube_koopman.identify.lifting import Constant, Delay, Lifting

__all__ = ["simulate_batch"]


def simulate_batch(A: np.ndarray, B: np.ndarray, lifting: Lifting, n_passthrough: int,
                   x_init: np.ndarray, v: np.ndarray, p0: np.ndarray | None = None,
                   relift: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Predict every episode with every model.

    Parameters
    ----------
    A : ndarray of shape (n_models, n_lifted, n_lifted)
    B : ndarray of shape (n_models, n_lifted, n_inputs)
    lifting : Lifting
        Fitted lifting of the plant states (shared by the models).
    n_passthrough : int
        Leading lifted states that are not lifted (controller states).
    x_init : ndarray of shape (n_episodes, n_delays + 1, n_states)
        Initial history of the plant states.
    v : ndarray of shape (n_episodes, n_samples, n_inputs)
        Inputs at every sample (those before ``n_delays`` are not used).
    p0 : ndarray of shape (n_episodes, n_passthrough), optional
        Passthrough state at sample ``n_delays`` (zero by default).
    relift : bool
        Re-lift the predicted original states at every step, or propagate
        the lifted state linearly.

    Returns
    -------
    x : ndarray of shape (n_models, n_episodes, n_samples, n_states)
        Predicted plant states; the first ``n_delays + 1`` samples are the
        initial condition. Non-finite where a prediction diverged.
    p : ndarray of shape (n_models, n_episodes, n_samples, n_passthrough)
        Predicted passthrough states (NaN before sample ``n_delays``).
    """
    d, m, n_p = lifting.n_delays_, lifting.n_features_in_, n_passthrough
    n_models, n_eps, T = A.shape[0], v.shape[0], v.shape[1]
    # Time-major storage: each step writes one contiguous block.
    x = np.full((T, n_models, n_eps, m), np.nan)
    p = np.full((T, n_models, n_eps, n_p), np.nan)
    x[:d + 1] = np.moveaxis(np.asarray(x_init, dtype=float), 1, 0)[:, None]
    p_d = np.zeros((n_eps, n_p)) if p0 is None else np.asarray(p0, dtype=float)
    p[d] = p_d
    lifted0 = lifting.transform(x_init)[:, 0, :]
    n_lifted = lifted0.shape[-1]
    z = np.broadcast_to(np.concatenate([p_d, lifted0], axis=-1), (n_models, n_eps, n_p + lifted0.shape[-1]))
    head, tail = _split_pointwise_head(lifting)
    # Pointwise steps then one Delay (e.g. monomials then delays), optionally then constants: the
    # new lifted state is the newest sample's features followed by the previous lifted state,
    # shifted, and the constants.
    shift = bool(tail) and isinstance(tail[0], Delay) and all(isinstance(s, Constant) for s in tail[1:])
    n_const = len(tail) - 1 if shift else 0
    ones = np.ones((n_models, n_eps, n_const))
    if relift and not shift:
        # Features of the leading pointwise steps for the last d + 1 samples: each step lifts
        # only the newest predicted sample and shifts the rest.
        history = _apply(head, np.moveaxis(x[:d + 1], 0, 2).copy())  # a copy: it is shifted in place
    rows = n_p + m if relift else A.shape[1]
    At = np.ascontiguousarray(A[:, :rows, :].transpose(0, 2, 1))  # (models, n_lifted, rows)
    Bt = np.ascontiguousarray(B[:, :rows, :].transpose(0, 2, 1))  # (models, n_inputs, rows)
    with np.errstate(all="ignore"):
        for k in range(d, T - 1):
            nxt = z @ At + v[None, :, k, :] @ Bt
            x[k + 1] = nxt[..., n_p:n_p + m]
            p[k + 1] = nxt[..., :n_p]
            if k % 256 == 0 and not np.any(np.isfinite(nxt)):
                break  # every prediction diverged; the rest stays NaN
            if not relift:
                z = nxt
                continue
            newest = _apply(head, nxt[..., None, n_p:n_p + m])[..., 0, :]
            if shift:
                lifted = np.concatenate([newest, z[..., n_p:n_p + n_lifted - n_const - newest.shape[-1]], ones],
                                        axis=-1)
            else:
                history[..., :-1, :] = history[..., 1:, :]
                history[..., -1, :] = newest
                lifted = _apply(tail, history)[..., 0, :]
            z = np.concatenate([nxt[..., :n_p], lifted], axis=-1)
    return np.moveaxis(x, 0, 2), np.moveaxis(p, 0, 2)


def _split_pointwise_head(lifting: Lifting) -> tuple[list, list]:
    """The fitted steps before the first one with delays, and the rest."""
    steps = list(lifting.steps_)
    for i, step in enumerate(steps):
        if step.n_delays:
            return steps[:i], steps[i:]
    return steps, []


def _apply(steps, X: np.ndarray) -> np.ndarray:
    for step in steps:
        X = step.transform(X)
    return X
