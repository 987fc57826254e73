"""Batched prediction: many linear Koopman models on many episodes at once.

Not the twin's closed loop (``sim.pendulum.closed_loop``, nonlinear physics) nor the rig's
(``daq.loop``, a backend tick by tick): this steps identified models, whose state is the lifting,
already closed with their controller (``estimators.structure.close_loop`` builds that loop's
matrices; it simulates nothing).

One implementation serves a single prediction and a regularization sweep
(one model per alpha, every validation episode). When the state is re-lifted
at every step only the rows of ``A`` and ``B`` that produce the passthrough
(controller) states and the original plant states are needed: the rest of
the lifted state is recomputed from the predicted history. On the
QUBE-Servo that is 4 rows of 57.

Three loops, the fastest that fits the lifting:

- the ring (:class:`_RingStepper`): pointwise steps (monomials, sin/cos), one
  delay step, optionally one radial basis on the delayed state, Coulomb
  friction shapes of delayed features, then constants: every lifting of the
  search and of the paper;
- the history loop (:class:`_HistoryStepper`): any other lifting, re-lifted
  from the last ``n_delays + 1`` predicted samples at every step;
- linear propagation of the lifted state (``relift=False``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from qube_koopman.identify.lifting import Constant, CoulombFriction, Delay, Lifting, Polynomial
from qube_koopman.identify.lifting.rbf import RadialBasis

__all__ = ["ring_capacity", "simulate_batch", "simulate_chunks"]

#: Samples whose input terms are computed together (bounds that array to a few MB).
_INPUT_CHUNK = 256
#: Passthrough rows from which the ring steps rows shared by every model in one product (below,
#: the batched product is as fast).
_MIN_SHARED_ROWS = 8
#: Largest set of permuted Koopman matrices and RBF centres the ring may keep (bytes).
_MAX_RING_BYTES = 64 * 2**20
#: Rows stepped per model (passthrough and plant states) from which the ring keeps one copy of
#: ``A^T`` and shifts the delayed features by a slot at every step instead of a permuted copy per
#: slot: a loop with a controller of many states (a designed one) has a product so much larger
#: than that copy that the copies' memory traffic dominates (a 71-state loop: 36 copies of 20
#: models' 144 x 73 rows, 60 MB, stepped in 300 us instead of 560 us); with the rig's PD (4 rows)
#: the copy is a quarter of the product and the copies stay in cache.
_SHIFT_FROM_ROWS = 8


def simulate_batch(
    A: np.ndarray,
    B: np.ndarray,
    lifting: Lifting,
    n_passthrough: int,
    x_init: np.ndarray,
    v: np.ndarray,
    p0: np.ndarray | None = None,
    relift: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
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
    # Time-major storage: each chunk writes one contiguous block.
    x = np.full((T, n_models, n_eps, m), np.nan)
    p = np.full((T, n_models, n_eps, n_p), np.nan)
    x[: d + 1] = np.moveaxis(np.asarray(x_init, dtype=float), 1, 0)[:, None]
    p[d] = np.zeros((n_eps, n_p)) if p0 is None else np.asarray(p0, dtype=float)

    def store(k0: int, chunk: np.ndarray, models: np.ndarray) -> None:
        if models.size == n_models:
            x[k0 : k0 + len(chunk)] = chunk[..., n_p:]
            p[k0 : k0 + len(chunk)] = chunk[..., :n_p]
        else:  # the others diverged: their samples stay NaN
            x[k0 : k0 + len(chunk), models] = chunk[..., n_p:]
            p[k0 : k0 + len(chunk), models] = chunk[..., :n_p]

    simulate_chunks(A, B, lifting, n_passthrough, x_init, v, p0, relift, store)
    return np.moveaxis(x, 0, 2), np.moveaxis(p, 0, 2)


def ring_capacity(lifting: Lifting, n_lifted: int, n_passthrough: int) -> int:
    """How many models of this shape the ring loop (the fastest) takes in one batch.

    It keeps a permuted copy of each model's used rows of ``A`` per delay slot; a larger batch
    is stepped by the slower history loop. Callers that batch models of their own choosing
    (:func:`~qube_koopman.identify.uncertainty.predict_groups`) split by this. A loop of many
    rows keeps one copy (it shifts its delayed features instead) and would take more models,
    but the batch's per-sample buffers grow with them (models x episodes x rows): its batches
    stay this size.
    """
    per_model = (lifting.n_delays_ + 1) * n_lifted * (n_passthrough + lifting.n_features_in_) * 8
    return max(1, _MAX_RING_BYTES // per_model)


def simulate_chunks(
    A: np.ndarray,
    B: np.ndarray,
    lifting: Lifting,
    n_passthrough: int,
    x_init: np.ndarray,
    v: np.ndarray,
    p0: np.ndarray | None,
    relift: bool,
    sink: Callable[[int, np.ndarray, np.ndarray], None],
    paired: bool = False,
) -> None:
    """:func:`simulate_batch`, handing the predictions to ``sink`` by chunks of samples.

    ``sink(k0, chunk, models)`` receives ``chunk`` of shape (n, len(models),
    n_episodes, n_passthrough + n_states): the predicted passthrough then plant
    states of samples ``k0 .. k0 + n - 1`` (from sample ``n_delays + 1`` on,
    time first) of the models whose indices ``models`` lists. A model leaves
    the chunks once every one of its predictions has diverged (its remaining
    samples would be non-finite); they stop when all have. The chunk is
    reused: copy what must outlive the call. A scorer that sums errors as they
    come never holds a whole prediction (memory stays flat in the episodes'
    length and the number of models).

    With ``paired``, groups of models predict episodes of their own: ``x_init``, ``v`` and
    ``p0`` have a leading axis of ``n_groups`` (``x_init`` of shape (n_groups, n_episodes,
    n_delays + 1, n_states), ...), and the models are ``n_groups`` consecutive groups of
    ``n_models // n_groups``. Ensembles on different episodes (the folds of a
    cross-validation) then share one pass over the samples, and every model stays in the
    chunks to the end (a diverged one gives non-finite samples).
    """
    d, m, n_p = lifting.n_delays_, lifting.n_features_in_, n_passthrough
    n_models = A.shape[0]
    x_init = np.asarray(x_init, dtype=float)
    if paired:
        n_groups, n_eps = v.shape[:2]
        if n_models % n_groups:
            raise ValueError(f"{n_models} models do not split into {n_groups} equal groups")
        each = n_models // n_groups  # the models of a group, on its episodes
        p_d = np.zeros((n_groups, n_eps, n_p)) if p0 is None else np.asarray(p0, dtype=float)
        lifted0 = lifting.transform(x_init.reshape((-1,) + x_init.shape[2:]))[:, 0, :].reshape(n_groups, n_eps, -1)
        p_d, lifted0 = np.repeat(p_d, each, axis=0), np.repeat(lifted0, each, axis=0)
        x_init = np.repeat(x_init, each, axis=0)
    else:
        n_eps = v.shape[0]
        p_d = np.zeros((n_eps, n_p)) if p0 is None else np.asarray(p0, dtype=float)
        lifted0 = lifting.transform(x_init)[:, 0, :]
    z = np.array(np.broadcast_to(np.concatenate([p_d, lifted0], axis=-1), (n_models, n_eps, n_p + lifted0.shape[-1])))
    rows = n_p + m if relift else A.shape[1]
    At = np.ascontiguousarray(A[:, :rows, :].transpose(0, 2, 1))  # (models, n_lifted, rows)
    Bt = np.ascontiguousarray(B[:, :rows, :].transpose(0, 2, 1))  # (models, n_inputs, rows)
    stepper: _Propagate | _RingStepper | _HistoryStepper
    if not relift:
        stepper = _Propagate(z, At)
    else:
        ring = _RingLayout.of(lifting, n_p, m, At)
        if ring is not None:
            stepper = _RingStepper(ring, z, rows)
        else:
            history = x_init.reshape((-1,) + x_init.shape[-2:]) if paired else x_init
            stepper = _HistoryStepper(lifting, z, At, history, n_p, paired)
    shared_B = None
    if (
        isinstance(stepper, _RingStepper)
        and stepper.ring.shared is not None
        and np.array_equal(Bt[:, :, :n_p], np.broadcast_to(Bt[:1, :, :n_p], Bt[:, :, :n_p].shape))
    ):
        shared_B = Bt[0, :, :n_p]  # the known controller's input rows: their terms once for every model
    with np.errstate(all="ignore"):
        _run(stepper, Bt, v, d, n_p + m, sink, paired, shared_B)


def _run(stepper, Bt: np.ndarray, v: np.ndarray, d: int, width: int, sink, paired: bool = False, shared_B=None) -> None:
    """Step from sample ``d``: input terms by chunks of samples, predictions to ``sink`` by the same chunks.

    A model whose every prediction has diverged by the end of a chunk is dropped from the
    rest of the run (its remaining samples would be non-finite): ``sink`` is told which
    models, by their index, each chunk holds. Paired models (each on its own episodes) all
    run to the end. ``shared_B`` (inputs x leading rows), the leading rows of every model's
    ``B^T``: their input terms are computed once per episode, not once per model.
    """
    T = v.shape[-2]
    n_eps = v.shape[1] if paired else v.shape[0]
    models = np.arange(Bt.shape[0])
    n_s = 0 if shared_B is None else shared_B.shape[-1]
    if n_s:
        Bt = np.ascontiguousarray(Bt[:, :, n_s:])
    buf = np.empty((_INPUT_CHUNK,) + stepper.z.shape[:2] + (width,))
    # The input terms of a chunk and their time-first copy, in two buffers kept for the run: fresh
    # arrays of this size (up to a few hundred MB for an ensemble) were mapped and page-faulted in
    # anew at every chunk.
    size = _INPUT_CHUNK * Bt.shape[0] * n_eps * Bt.shape[-1]
    terms_buffer, u_buffer = np.empty(size), np.empty(size)
    for c0 in range(d, T - 1, _INPUT_CHUNK):
        n = min(_INPUT_CHUNK, T - 1 - c0)
        shape = (Bt.shape[0], n_eps * n, Bt.shape[-1])
        terms = terms_buffer[: np.prod(shape)].reshape(shape)
        if paired:  # each group's inputs times its models' B: (groups, models per group, episodes x n, rows)
            chunk = v[:, :, c0 : c0 + n].reshape(v.shape[0], 1, -1, v.shape[-1])
            grouped = (v.shape[0], -1)
            np.matmul(chunk, Bt.reshape(grouped + Bt.shape[1:]), out=terms.reshape(grouped + shape[1:]))
        else:
            np.matmul(v[:, c0 : c0 + n].reshape(1, -1, v.shape[-1]), Bt, out=terms)
        # Time first, so that each step adds one contiguous block.
        u_terms = u_buffer[: terms.size].reshape(n, Bt.shape[0], n_eps, Bt.shape[-1])
        np.copyto(u_terms, terms.reshape(Bt.shape[0], n_eps, n, Bt.shape[-1]).transpose(2, 0, 1, 3))
        if n_s:  # (n, groups, 1, episodes, n_s): each group's episodes, for all its models
            per_episode = v[..., c0 : c0 + n, :] @ shared_B
            per_episode = per_episode if paired else per_episode[None]
            shared_terms = np.ascontiguousarray(np.moveaxis(per_episode, -2, 0)[:, :, None])
            for j in range(n):
                stepper.step(u_terms[j], buf[j], shared_terms[j])
        else:
            for j in range(n):
                stepper.step(u_terms[j], buf[j])
        sink(c0 + 1, buf[:n], models)
        if paired:
            continue
        alive = np.isfinite(buf[n - 1]).any(axis=(1, 2))
        if not alive.all():
            if not alive.any():
                break
            stepper.keep(alive)
            models, Bt, buf = models[alive], Bt[alive], np.ascontiguousarray(buf[:, alive])


class _Propagate:
    """The lifted state propagated linearly: ``z_{k+1} = A z_k + B v_k``."""

    def __init__(self, z: np.ndarray, At: np.ndarray) -> None:
        self.z, self.At = z, At

    def step(self, u_term: np.ndarray, out: np.ndarray) -> None:
        self.z = self.z @ self.At
        self.z += u_term
        out[...] = self.z[..., : out.shape[-1]]

    def keep(self, models: np.ndarray) -> None:
        """Only these models from now on (a boolean mask over the current ones)."""
        self.z, self.At = self.z[models], self.At[models]


class _HistoryStepper:
    """Any lifting, re-lifted at every step from the features of the last ``d + 1`` samples.

    The leading pointwise steps lift only the newest predicted sample; the
    history of their features shifts by one; the rest of the lifting is
    applied to that history.
    """

    def __init__(
        self, lifting: Lifting, z: np.ndarray, At: np.ndarray, x_init: np.ndarray, n_p: int, paired: bool = False
    ) -> None:
        self.head, self.tail = _split_pointwise_head(lifting)
        self.z, self.At, self.n_p = z, At, n_p
        history = _apply(self.head, np.asarray(x_init, dtype=float))  # (episodes, d + 1, features)
        if paired:  # (models x episodes, ...): each model's own episodes
            history = history.reshape(z.shape[:2] + history.shape[1:])
        self.history = np.array(np.broadcast_to(history, z.shape[:2] + history.shape[-2:]))

    def step(self, u_term: np.ndarray, out: np.ndarray) -> None:
        nxt = self.z @ self.At
        nxt += u_term
        out[...] = nxt
        history = self.history
        history[..., :-1, :] = history[..., 1:, :]
        history[..., -1, :] = _apply(self.head, nxt[..., None, self.n_p :])[..., 0, :]
        self.z = np.concatenate([nxt[..., : self.n_p], _apply(self.tail, history)[..., 0, :]], axis=-1)

    def keep(self, models: np.ndarray) -> None:
        """Only these models from now on (a boolean mask over the current ones)."""
        self.z, self.At, self.history = self.z[models], self.At[models], self.history[models]


@dataclass
class _RingLayout:
    """Where a ring-shaped lifting keeps its features in the lifted state.

    The lifted state is ``[passthrough (n_p), the pointwise features of the
    last d + 1 samples newest first (slots x n_feat), radial basis values of
    that delayed vector (n_rbf), Coulomb friction shapes (n_friction),
    constants]``. In the ring the delayed features stay in place and the
    oldest slot takes the newest sample; the rows of ``A^T`` (and the RBF
    centres' columns) are permuted to match, one permuted copy per ring
    position. A friction shape reads two ages of one delayed feature, found
    in the ring from its position. With ``shift`` (a loop of many rows: see
    ``_SHIFT_FROM_ROWS``) the ring stays at position 0, the only copy kept,
    and the delayed features move one slot older at every step instead.
    """

    head: list
    n_p: int
    n_feat: int
    slots: int
    rbf: RadialBasis | None
    perms: list[np.ndarray]
    # The passthrough rows' permuted A^T when every model has the same (a known controller's state
    # update wrapped around each fitted plant): one matrix product for all models at once; perms
    # then hold only the plant rows. Its rows stop at the last column of the lifted state it reads.
    # None when they differ.
    shared: list[np.ndarray] | None
    centers: list[np.ndarray] | None
    centers_sq: np.ndarray | None
    picks: list[np.ndarray] | None
    friction: list[tuple[int, int, float]]  # per friction step: (feature in a slot, age of the past, width)
    shift: bool = False  # one copy at position 0, the delayed features shifted at every step

    @classmethod
    def of(cls, lifting: Lifting, n_p: int, m: int, At: np.ndarray) -> "_RingLayout | None":
        """The layout of ``lifting``, or None when it is not ring-shaped or the ring is too large."""
        head, tail = _split_pointwise_head(lifting)
        if not tail or not isinstance(tail[0], Delay):
            return None
        rest = list(tail[1:])
        rbf = rest.pop(0) if rest and isinstance(rest[0], RadialBasis) else None
        friction = []
        while rest and isinstance(rest[0], CoulombFriction):
            friction.append(rest.pop(0))
        if not all(isinstance(step, Constant) for step in rest):
            return None
        n_feat = _apply(head, np.zeros((1, m))).shape[-1]
        slots = tail[0].n_delays + 1
        n_shift = slots * n_feat
        if any(f.feature >= n_feat or f.past_index_ >= n_shift for f in friction):
            return None  # a friction shape of something other than the delayed features
        n_rbf = 0 if rbf is None else rbf.centers_.shape[0]
        shift = At.shape[-1] >= _SHIFT_FROM_ROWS
        if (1 if shift else slots) * (At.nbytes + n_shift * n_rbf * 8) > _MAX_RING_BYTES:
            return None
        # Ring position q: slot s holds the sample of age (s - q) mod slots.
        order = [
            np.array([((s - q) % slots) * n_feat + c for s in range(slots) for c in range(n_feat)])
            for q in range(1 if shift else slots)
        ]
        rows_of = [np.r_[np.arange(n_p), n_p + o, np.arange(n_p + n_shift, At.shape[1])] for o in order]
        shared = None
        if (
            n_p >= _MIN_SHARED_ROWS
            and At.shape[0] > 1
            and np.array_equal(At[:, :, :n_p], np.broadcast_to(At[:1, :, :n_p], At[:, :, :n_p].shape))
        ):
            shared = [At[0][r][:, :n_p] for r in rows_of]
            # A known controller reads its own states and the fed-back plant states, the leading
            # columns of the lifted state: the product skips the rows of A^T that are zero for every
            # position (exactly: the dropped terms are zeros).
            reads = 1 + max(int(np.flatnonzero(np.any(S != 0, axis=1)).max(initial=0)) for S in shared)
            shared = [np.ascontiguousarray(S[:reads]) for S in shared]
            At = At[:, :, n_p:]
        perms = [np.ascontiguousarray(At[:, r, :]) for r in rows_of]
        centers = None if rbf is None else [np.ascontiguousarray(rbf.centers_[:, o].T) for o in order]
        centers_sq = None if rbf is None else np.einsum("ij,ij->i", rbf.centers_, rbf.centers_)
        return cls(
            head,
            n_p,
            n_feat,
            slots,
            rbf,
            perms,
            shared,
            centers,
            centers_sq,
            _monomial_picks(head, n_p, m),
            [(f.feature, f.past_index_ // n_feat, f.width) for f in friction],
            shift,
        )

    def write_newest(self, z: np.ndarray, y: np.ndarray, q: int) -> None:
        """The newest sample's pointwise features (from ``y``: its rows, then ones) into slot ``q``."""
        lo = self.n_p + q * self.n_feat
        slot = z[..., lo : lo + self.n_feat]
        rows = y.shape[-1] - 1
        if self.picks is None:
            slot[...] = _apply(self.head, y[..., None, self.n_p : rows])[..., 0, :]
        elif len(self.picks) == 1:  # order 1: the states themselves
            np.copyto(slot, y.take(self.picks[0], axis=-1))
        else:  # ndarray.take: faster than fancy indexing on these small arrays (and than np.take's wrapper)
            np.multiply(y.take(self.picks[0], axis=-1), y.take(self.picks[1], axis=-1), out=slot)
            for extra in self.picks[2:]:
                slot *= y.take(extra, axis=-1)

    def write_rbf(self, z: np.ndarray, q: int) -> None:
        """The radial basis values of the delayed vector at ring position ``q``."""
        assert self.rbf is not None and self.centers is not None and self.centers_sq is not None  # of an RBF step
        lo, n_shift = self.n_p, self.slots * self.n_feat
        n_rbf = self.centers_sq.size
        z[..., lo + n_shift : lo + n_shift + n_rbf] = self.rbf.kernel_values(
            z[..., lo : lo + n_shift], self.centers[q], self.centers_sq
        )

    def write_friction(self, z: np.ndarray, q: int) -> None:
        """The friction shapes at ring position ``q``: the age-``a`` sample sits in slot ``(q + a) % slots``."""
        lo = self.n_p + self.slots * self.n_feat + (0 if self.centers_sq is None else self.centers_sq.size)
        newest = self.n_p + q * self.n_feat
        for j, (c, age, width) in enumerate(self.friction):
            past = self.n_p + ((q + age) % self.slots) * self.n_feat
            np.tanh((z[..., newest + c] - z[..., past + c]) / width, out=z[..., lo + j])


def _monomial_picks(head, n_p: int, m: int) -> list[np.ndarray] | None:
    """Columns of ``[passthrough, states, 1]`` whose products give one Polynomial head's features.

    ``picks[j][i]`` is the column of the j-th factor of feature i (the trailing column of ones
    pads lower-degree monomials). None for any other head: it is applied as it is.
    """
    if len(head) != 1 or not isinstance(head[0], Polynomial):
        return None
    monomials = head[0].monomials_
    order = max(len(c) for c in monomials)
    return [np.array([n_p + c[j] if j < len(c) else n_p + m for c in monomials]) for j in range(order)]


class _RingStepper:
    """The re-lifted step of a ring-shaped lifting (see :class:`_RingLayout`).

    Each sample costs a batched product with the permuted ``A^T``, its input
    term, and the newest sample's features written over the oldest (and, with
    a radial basis, one product with the permuted centres).
    """

    def __init__(self, ring: _RingLayout, z: np.ndarray, rows: int) -> None:
        self.ring, self.z, self.q = ring, z, 0
        # y: the newest sample's passthrough and states, then a column of ones for padded factors.
        self.y = np.ones(z.shape[:2] + (rows + 1,))
        self.newest = self.y[..., :rows]

    def step(self, u_term: np.ndarray, out: np.ndarray, shared_term: np.ndarray | None = None) -> None:
        """One sample; ``shared_term`` (groups, 1, episodes, n_p): the shared rows' input terms, when
        ``u_term`` holds only the plant rows'."""
        ring, z = self.ring, self.z
        # The sample is computed in ``out`` (contiguous: the product and the sum run without a
        # strided copy), then copied beside ``y``'s column of ones for the features.
        if ring.shared is None:
            np.matmul(z, ring.perms[self.q], out=out)
        else:  # the shared passthrough rows in one product over every model's episodes, then the plant rows
            n_p = ring.n_p
            shared = ring.shared[self.q]
            flat = z.reshape(-1, z.shape[-1])[:, : shared.shape[0]]  # the columns it reads
            if shared_term is None:
                out[..., :n_p] = (flat @ shared).reshape(z.shape[:2] + (n_p,))
            else:  # splitting the models' axis by groups keeps ``out``'s view
                grouped = (shared_term.shape[0], -1) + z.shape[1:2] + (n_p,)
                np.add((flat @ shared).reshape(grouped), shared_term, out=out[..., :n_p].reshape(grouped))
            out[..., n_p:] = np.matmul(z, ring.perms[self.q])
        if shared_term is None:
            out += u_term
        else:
            out[..., ring.n_p :] += u_term
        newest = self.newest
        newest[...] = out
        if ring.shift:  # every delayed feature one slot older, the oldest dropped: slot 0 takes the newest
            lo, width = ring.n_p, ring.n_feat
            z[..., lo + width : lo + ring.slots * width] = z[..., lo : lo + (ring.slots - 1) * width]
            q = 0
        else:
            self.q = q = (self.q - 1) % ring.slots  # the oldest slot takes the newest sample
        ring.write_newest(z, self.y, q)
        if ring.rbf is not None:
            ring.write_rbf(z, q)
        if ring.friction:
            ring.write_friction(z, q)
        z[..., : ring.n_p] = out[..., : ring.n_p]

    def keep(self, models: np.ndarray) -> None:
        """Only these models from now on (a boolean mask over the current ones)."""
        self.z, self.y = self.z[models], self.y[models]
        self.newest = self.y[..., :-1]
        self.ring.perms = [perm[models] for perm in self.ring.perms]


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
