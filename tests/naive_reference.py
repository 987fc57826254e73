"""The reference code's way of predicting, kept simple on purpose: one model,
one episode, the full lifting recomputed from the predicted history at every
step. Tests check the fast predictor against it; bench/ times it."""

from __future__ import annotations

import numpy as np


def naive_predict(model, x_init: np.ndarray, v: np.ndarray, p0: np.ndarray | None = None) -> np.ndarray:
    """Predicted plant states of one episode (re-lifting at every step)."""
    d, m, n_p = model.n_delays, model.n_states, model.n_passthrough
    T = v.shape[0]
    x = np.full((T, m), np.nan)
    x[: d + 1] = x_init
    p = np.zeros(n_p) if p0 is None else np.asarray(p0, dtype=float)
    with np.errstate(all="ignore"):
        for k in range(d, T - 1):
            z = np.concatenate([p, model.lifting.transform(x[k - d : k + 1])[0]])
            nxt = model.A @ z + model.B @ v[k]
            x[k + 1] = nxt[n_p : n_p + m]
            p = nxt[:n_p]
    return x
