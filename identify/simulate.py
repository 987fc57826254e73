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
    if relift and shift:
        with np.errstate(all="ignore"):
            if _relift_shifting(np.array(z), At, Bt, v, x, p, d, head, n_p, n_lifted - n_const):
                return np.moveaxis(x, 0, 2), np.moveaxis(p, 0, 2)
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


#: Samples whose input terms are computed together (bounds that array to a few MB).
_INPUT_CHUNK = 256
#: Largest set of row-permuted Koopman matrices the ring buffer may keep (bytes).
_MAX_RING_BYTES = 64 * 2**20


def _monomial_columns(head, m: int) -> list[np.ndarray] | None:
    """Column indices whose products give the head's features of one sample, if it is one Polynomial.

    ``cols[j][i]`` is the j-th factor of feature i among the sample's ``m`` states, or ``m`` for
    a factor of 1 (lower-degree monomials are padded with it). None for any other head.
    """
    from qube_koopman.identify.lifting import Polynomial

    if len(head) != 1 or not isinstance(head[0], Polynomial):
        return None
    monomials = head[0].monomials_
    order = max(len(c) for c in monomials)
    return [np.array([c[j] if j < len(c) else m for c in monomials]) for j in range(order)]


def _relift_shifting(z, At, Bt, v, x, p, d: int, head, n_p: int, n_shifting: int) -> bool:
    """The re-lifted prediction loop for monomials, one delay step and constants, in a ring buffer.

    ``z`` (models, episodes, n_p + lifted): the passthrough states, then the features of the
    last ``d + 1`` samples newest first (``n_shifting`` values), then constants. Instead of
    shifting the delayed features every sample, they stay in place in a ring and the rows
    of ``At`` are permuted to match (one permuted copy per ring position): each sample
    costs a batched product, its input term (precomputed by chunks), and the newest
    sample's monomials written over the oldest. Fills ``x`` and ``p`` (time-major) from
    sample ``d + 1`` on. Returns False, doing nothing, when the head is not one
    Polynomial or the permuted copies would exceed ``_MAX_RING_BYTES``.
    """
    T, rows = v.shape[1], At.shape[2]
    m = x.shape[-1]
    cols = _monomial_columns(head, m)
    if cols is None:
        return False
    n_feat = cols[0].size
    slots = n_shifting // n_feat
    if slots * At.nbytes > _MAX_RING_BYTES:
        return False
    lo = n_p
    # ring position q: slot s holds the sample of age (s - q) mod slots
    perms = []
    for q in range(slots):
        ages = [(s - q) % slots for s in range(slots)]
        idx = np.r_[np.arange(lo), [lo + a * n_feat + c for a in ages for c in range(n_feat)],
                    np.arange(lo + n_shifting, At.shape[1])]
        perms.append(np.ascontiguousarray(At[:, idx, :]))
    # Y: the newest sample's passthrough and states, with a column of ones for padded factors.
    y = np.ones(z.shape[:2] + (rows + 1,))
    out = y[..., :rows]
    picks = [np.where(c == m, rows, n_p + c) for c in cols]
    q = 0
    for c0 in range(d, T - 1, _INPUT_CHUNK):
        c1 = min(c0 + _INPUT_CHUNK, T - 1)
        u_terms = np.matmul(v[:, c0:c1].reshape(1, -1, v.shape[-1]), Bt).reshape(
            Bt.shape[0], v.shape[0], c1 - c0, rows)
        for j, k in enumerate(range(c0, c1)):
            np.matmul(z, perms[q], out=out)
            out += u_terms[:, :, j]
            x[k + 1] = out[..., n_p:n_p + m]
            p[k + 1] = out[..., :n_p]
            q = (q - 1) % slots  # the oldest slot takes the newest sample
            slot = z[..., lo + q * n_feat:lo + (q + 1) * n_feat]
            if len(picks) == 1:  # order 1: the states themselves
                np.copyto(slot, y[..., picks[0]])
            else:
                np.multiply(y[..., picks[0]], y[..., picks[1]], out=slot)
            for extra in picks[2:]:
                slot *= y[..., extra]
            z[..., :n_p] = out[..., :n_p]
        if not np.any(np.isfinite(out)):
            break  # every prediction diverged; the rest stays NaN
    return True


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
