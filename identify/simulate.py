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

from identify.lifting import Lifting

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
    x = np.full((n_models, n_eps, T, m), np.nan)
    p = np.full((n_models, n_eps, T, n_p), np.nan)
    x[:, :, :d + 1, :] = x_init
    p_d = np.zeros((n_eps, n_p)) if p0 is None else np.asarray(p0, dtype=float)
    p[:, :, d, :] = p_d
    lifted0 = lifting.transform(x_init)[:, 0, :]
    z = np.broadcast_to(np.concatenate([p_d, lifted0], axis=-1), (n_models, n_eps, n_p + lifted0.shape[-1]))
    rows = n_p + m if relift else A.shape[1]
    At = np.ascontiguousarray(A[:, :rows, :].transpose(0, 2, 1))  # (models, n_lifted, rows)
    Bt = np.ascontiguousarray(B[:, :rows, :].transpose(0, 2, 1))  # (models, n_inputs, rows)
    with np.errstate(all="ignore"):
        for k in range(d, T - 1):
            nxt = z @ At + v[None, :, k, :] @ Bt
            x[:, :, k + 1, :] = nxt[..., n_p:n_p + m]
            p[:, :, k + 1, :] = nxt[..., :n_p]
            if k % 256 == 0 and not np.any(np.isfinite(nxt)):
                break  # every prediction diverged; the rest stays NaN
            if relift:
                lifted = lifting.transform(x[:, :, k + 1 - d:k + 2, :])[..., 0, :]
                z = np.concatenate([nxt[..., :n_p], lifted], axis=-1)
            else:
                z = nxt
    return x, p
