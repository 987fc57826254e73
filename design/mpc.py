"""A condensed linear model predictive controller on the identified plant's history.

The prediction model is the LQ design's (:func:`design.lq.augment`): the plant as a shift register
of its last ``d + 1`` measurements and the integral of the arm's tracking error, in the
coordinates of the tracking errors, ``z_k = [s_k - s_ref; w_k]`` (``s_ref``: the references held
over the horizon), ``z_{k+1} = F_a z_k + G_a u_k``. Over a horizon of ``N`` inputs
``U = [u_0 .. u_{N-1}]`` the predicted states are ``Z = Phi z_0 + Gamma U``, built once (the
condensed form), and the tick's problem is a QP in ``U`` alone (why this predictor and not Korda & Mezić's
lifted map ``z_{k+1} = A z_k + B u_k``, measured on the paper's held-out episodes: :mod:`design.predictors`,
docs/design.md)::

    minimize    sum_{i<N} z_i' Q z_i + u_i' R u_i + z_N' P z_N  +  rho sum_i (slack_i)^2
    subject to  -V - f <= u_i <= V - f                    (the voltage limit; f the feedforward)
                |theta_i| <= theta_max + slack_i, i = 1..N  (the arm inside a margin of the stop)

``Q``, ``R`` are the LQ weights; ``P`` the infinite-horizon LQ's Riccati solution, so that without
active constraints the MPC's first input is the LQ gain's ``u = -K z`` exactly. The arm's bound is
soft: the slack's quadratic penalty, minimized out, is ``rho max(0, |theta_i| - theta_max)^2``, so
the problem is a box-constrained QP with a piecewise quadratic term and always feasible.

Two solvers of the same problem (``solver`` setting):

- ``"newton"`` (the default): a projected Newton method on the box (Bertsekas' two-metric
  projection) with the penalty's generalized Hessian, warm-started from the previous plan shifted
  by one tick. Kept because it is faster at the same accuracy: in ``qube-run``'s loop on the twin
  (bench/bench_mpc.py, 71-state plant, horizon 20) it takes 1 iteration at p99 and about 50 us a
  tick (p50; p99 110 us of CPU time), OSQP warm-started on the same QP about 50 iterations and
  twice that (p50 104 us, p99 198 us): its per-call overhead and ADMM iterations cost more than a
  Cholesky factor of an N x N matrix, which a tick with nothing binding does not even need.
- ``"osqp"``: OSQP on the same QP with one slack per predicted step, warm-started.

Offset-free control (``settings.offset_free``, :class:`MpcDisturbance`): from the model file's
disturbance model, each tick filters a load at the plant input and a rate on the arm's angle (one
disturbance per measured angle, :func:`mpc_disturbance`) from the measurements with a steady-state
Kalman gain, predicts them constant over the horizon and solves the same QP about the steady state
they imply (the arm at its reference, the voltage cancelling the load): a constant load, or a
plant that is not the model's, leaves no offset, which without the arm's integral it otherwise
does (Pannocchia & Rawlings 2003; Maeder, Borrelli & Morari 2009).

A tick whose solve does not finish within its budget (``time_budget``, s, checked between
iterations; OSQP's own ``time_limit``) or fails applies a fallback: the previous plan's next input,
or with no plan the LQ gain, clipped to the limit; the controller counts those ticks.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from qube_koopman.core.qube import THETA_LIMIT
from qube_koopman.design.lq import Weights, augment
from qube_koopman.design.plant import DesignError, LinearPlant
from qube_koopman.identify.models.disturbance import ENTRIES as DISTURBANCE_ENTRIES
from qube_koopman.identify.models.disturbance import DisturbanceModel, steady_state_gains
from qube_koopman.identify.models.identified import IdentifiedModel

__all__ = [
    "MpcSettings",
    "MpcDisturbance",
    "OFFSET_FREE_ENTRIES",
    "model_disturbance",
    "mpc_disturbance",
    "MpcProblem",
    "SolveResult",
    "build_problem",
    "solve_newton",
    "OsqpSolver",
    "MpcRuntime",
    "SOLVER_STATUS",
]

#: The solve's status codes, as the log records them per tick.
SOLVER_STATUS = {"solved": 0, "max_iterations": 1, "timeout": 2, "failed": 3}


@dataclass(frozen=True)
class MpcSettings:
    """The MPC's horizon, limits and solver settings.

    Parameters
    ----------
    horizon : int
        Inputs predicted, ``N``. The default, 20 ticks (40 ms), covers the pendulum's unstable
        time constant (about 0.1 s) partly; the terminal LQ cost carries the rest, and a solve
        stays well inside the tick's budget.
    voltage_limit : float
        ``|V| <=`` this (V); the rig's clamp is 10 V.
    theta_margin : float
        The arm is kept within ``THETA_LIMIT - theta_margin`` (rad) of upright, softly.
    theta_penalty : float
        ``rho``: the quadratic penalty per rad^2 of the arm's excess.
    solver : {"newton", "osqp"}
        The QP solver.
    max_iterations : int
        Of the projected Newton method (OSQP: its own ``max_iter`` is 50 times this).
    tolerance : float
        Optimality: the projected gradient's largest entry (newton), or OSQP's eps_abs/eps_rel.
    time_budget : float
        Seconds a solve may take before the tick applies the fallback.
    offset_free : bool
        Use the estimated disturbance (:class:`MpcDisturbance`) in the prediction and the
        steady-state target: the arm tracks its reference with no offset under a constant load.
        Needs the controller's disturbance model; without one the MPC is the same either way.
    """

    horizon: int = 20
    voltage_limit: float = 10.0
    theta_margin: float = 0.2
    theta_penalty: float = 1e4
    solver: str = "newton"
    max_iterations: int = 20
    tolerance: float = 1e-7
    time_budget: float = 1.0e-3
    offset_free: bool = False

    def __post_init__(self) -> None:
        if not (isinstance(self.horizon, int) and 1 <= self.horizon <= 200):
            raise DesignError(f"--horizon must be a whole number of ticks from 1 to 200, got {self.horizon!r}")
        if not (math.isfinite(self.voltage_limit) and 0 < self.voltage_limit <= 10.0):
            raise DesignError(f"--voltage-limit must be above 0 and at most the rig's 10 V, got {self.voltage_limit!r}")
        if not (0 <= self.theta_margin < THETA_LIMIT):
            raise DesignError(f"the arm's margin must be in [0, {THETA_LIMIT:.4g}) rad, got {self.theta_margin!r}")
        if self.solver not in ("newton", "osqp"):
            raise DesignError(f'the MPC solver must be "newton" or "osqp", got {self.solver!r}')
        if not (self.theta_penalty > 0 and self.tolerance > 0 and self.time_budget > 0 and self.max_iterations >= 1):
            raise DesignError("the MPC's penalty, tolerance, time budget and iterations must be positive")
        if not isinstance(self.offset_free, bool):
            raise DesignError(f"offset_free must be true or false, got {self.offset_free!r}")

    def as_dict(self) -> dict:
        """Plain data, for the controller file."""
        return asdict(self)


def model_disturbance(model: IdentifiedModel) -> DisturbanceModel | None:
    """The loaded model file's disturbance model, or None: the one read of the model file the MPC makes.

    Parameters
    ----------
    model : IdentifiedModel
        What :func:`identify.models.model_file.load_model` returns.
    """
    return model.disturbance


#: The disturbances the offset-free MPC estimates by default: a load at the plant input and a rate on the
#: arm's angle, as many as measured angles (:func:`mpc_disturbance`).
OFFSET_FREE_ENTRIES = ("input", "theta")


@dataclass(frozen=True, eq=False)
class MpcDisturbance:
    """The disturbances an MPC estimates each tick: where they enter, the plant they are estimated on, the filter gain.

    On the design plant ``x_{k+1} = F_x s_k + b v_k + G d_k`` (``s_k`` the measured history, ``v_k``
    the plant input: the controller's output plus the feedforward), ``G``'s column of each
    disturbance is ``b`` for a load at the plant input (volts) and the angle's unit vector for a
    rate on theta or alpha (rad per tick). The plant's affine term (a ``Constant`` lifting step) is
    left out, as the LQ design and the MPC's prediction leave it: the estimate takes up what of it
    the disturbances explain. (Kept, the model's constant, a fit to closed-loop episodes, sets a
    target the plant does not rest at: on the twin an offset of 0.01 rad with no load at all.) Each
    tick, from the one-step residual ``r_k = x_k - (F_x s_{k-1} + b v_{k-1})``, the steady-state
    Kalman filter in innovations form (with one disturbance
    :func:`identify.models.disturbance.filter_disturbance`, the same recursion)::

        p_k = pole f_{k-1},   f_k = p_k + L (r_k - G p_k),   d_k = pole f_k

    Parameters
    ----------
    entries : str or tuple of str
        Where each disturbance enters (``"input"``, ``"theta"``, ``"alpha"``), at most one per
        measured angle; a string for one.
    pole : float
        ``d_{k+1} = pole d_k + w_k``; offset-free control needs a random walk (1).
    gain : ndarray of shape (n_d, 2), or (2,) with one disturbance
        ``L``.
    rows : ndarray of shape (2, n)
        ``F_x``, the plant's one-step map on its history (newest sample first).
    input : ndarray of shape (2,)
        ``b``.
    """

    entries: tuple[str, ...]
    pole: float
    gain: np.ndarray
    rows: np.ndarray
    input: np.ndarray

    def __post_init__(self) -> None:
        entries = (self.entries,) if isinstance(self.entries, str) else tuple(self.entries)
        object.__setattr__(self, "entries", entries)
        for entry in entries:
            if entry not in DISTURBANCE_ENTRIES:
                raise DesignError(f"unknown disturbance entry {entry!r} (one of {', '.join(DISTURBANCE_ENTRIES)})")
        m = len(self.input)
        if not (1 <= len(entries) <= m) or len(set(entries)) != len(entries):
            raise DesignError(f"the MPC estimates 1 to {m} distinct disturbances, got {', '.join(entries) or 'none'}")
        gain = np.asarray(self.gain, dtype=float)
        gain = gain.reshape(1, -1) if gain.ndim == 1 else gain
        object.__setattr__(self, "gain", gain)
        if gain.shape != (len(entries), m) or np.shape(self.rows)[0] != m:
            raise DesignError(f"the disturbance's gain must have {len(entries)} row(s) of {m}, one per measured angle")
        if not (0.0 <= self.pole <= 1.0) or not np.all(np.isfinite(gain)):
            raise DesignError(f"the disturbance's pole {self.pole!r} must be in [0, 1] and its gain finite")
        if np.linalg.matrix_rank(self.direction) < len(entries):
            raise DesignError(
                f"the disturbances {', '.join(entries)} move the angles alike: the filter cannot tell them apart"
            )

    @property
    def direction(self) -> np.ndarray:
        """``G`` (2 x n_d): each disturbance's unit effect on the next measurement."""
        m = len(self.input)
        G = np.zeros((m, len(self.entries)))
        for j, entry in enumerate(self.entries):
            if entry == "input":
                G[:, j] = self.input
            else:
                G[DISTURBANCE_ENTRIES.index(entry) - 1, j] = 1.0
        return G

    def target_map(self) -> np.ndarray:
        """``T`` (2 x (1 + n_d)): the steady state ``[alpha_ss, v_ss] = T @ [r_theta, d]``, the arm at its reference.

        Solves ``(I - sum_j A_j) x_ss = b v_ss + G d`` for ``x_ss = [r_theta, alpha_ss]``
        (``A_j``: ``F_x``'s block on ``x_{k-j}``), the target calculation of offset-free MPC
        (Pannocchia & Rawlings 2003): the arm at its reference, the pendulum and the voltage where
        the plant, under the constant disturbances, rests.

        Raises
        ------
        DesignError
            When the plant has no such steady state (the voltage and the pendulum cannot hold the arm).
        """
        m = len(self.input)
        rows = np.asarray(self.rows, dtype=float)
        A_sum = rows.reshape(m, -1, m).sum(axis=1)
        I_A = np.eye(m) - A_sum
        M = np.column_stack([I_A[:, 1], -np.asarray(self.input, dtype=float)])
        if np.linalg.cond(M) > 1e12:
            raise DesignError(
                "offset-free MPC: the plant has no steady state with the arm at its reference (the pendulum "
                "and the voltage cannot balance a constant disturbance); design with --no-offset-free"
            )
        rhs = np.column_stack([-I_A[:, 0], self.direction])
        return np.linalg.solve(M, rhs)

    def as_dict(self) -> dict:
        """The controller file's ``disturbance`` table (the plant's rows are the file's ``plant_rows``)."""
        return {
            "entries": list(self.entries),
            "pole": float(self.pole),
            "gain": [[float(v) for v in row] for row in self.gain],
        }


def mpc_disturbance(
    plant: LinearPlant,
    disturbance: DisturbanceModel,
    integrate: bool = False,
    entries: tuple[str, ...] | None = None,
) -> MpcDisturbance:
    """The model file's disturbance model on the design plant (its affine term left out): what the MPC estimates.

    Parameters
    ----------
    plant : LinearPlant
    disturbance : DisturbanceModel
        The model file's. Alone (``entries`` None or its own entry) its ``entry``, ``pole`` and
        ``gain`` are used as they are.
    integrate : bool
        A first-order disturbance becomes a random walk with the same ``q`` and ``R`` and the
        Kalman gain of pole 1 (:meth:`DisturbanceModel.integrated`): what offset-free control needs
        to reject a constant load (nothing refitted).
    entries : tuple of str, optional
        The disturbances to estimate, when not the model file's one alone; offset-free control's
        default is :data:`OFFSET_FREE_ENTRIES`, one per measured angle, since with fewer
        disturbances than measured outputs a plant the model did not see leaves an offset (the
        filter's innovations need not vanish at rest, and the target then misses the arm's
        reference: Pannocchia & Rawlings 2003, Maeder, Borrelli & Morari 2009). Each gets the
        model file's ``R`` and a ``q`` that gives it alone the model's disturbance's filter speed:
        a scalar filter's gain depends on ``q g' R^-1 g`` only, so ``q_j = q g' R^-1 g / g_j' R^-1 g_j``
        (``g`` the model's disturbance's direction, ``g_j`` this one's); the filter's gain is the
        Kalman gain of those covariances (:func:`identify.models.disturbance.steady_state_gains`),
        with the model's pole, or 1 with ``integrate``. Nothing is refitted.

    Returns
    -------
    MpcDisturbance
    """
    m = plant.n_measured
    rows, b = plant.F[:m].copy(), plant.G[:m, 0].copy()
    own = MpcDisturbance((str(disturbance.entry),), float(disturbance.pole), disturbance.gain, rows, b)
    if entries is None or tuple(entries) == own.entries:
        if not integrate:
            return own
        walk = disturbance.integrated(own.direction[:, 0])  # itself when it is a random walk already
        return replace(own, pole=walk.pole, gain=walk.gain)
    pole = 1.0 if integrate else float(disturbance.pole)
    out = MpcDisturbance(tuple(entries), pole, np.zeros((len(entries), m)), rows, b)
    R = np.asarray(disturbance.R, dtype=float)
    speed = float(disturbance.q) * _information(own.direction[:, 0], R)  # q g' R^-1 g
    G = out.direction
    Q = np.diag([speed / _information(G[:, j], R) for j in range(G.shape[1])])
    gain, _ = steady_state_gains(G, pole, Q, R)
    return replace(out, gain=gain)


def _information(g: np.ndarray, R: np.ndarray) -> float:
    """``g' R^-1 g``: how much one sample's residual says about a unit disturbance along ``g``."""
    return float(g @ np.linalg.solve(R, g))


@dataclass(frozen=True, eq=False)
class MpcProblem:
    """The condensed problem: what a tick needs to set up its QP from ``z_0``.

    Parameters
    ----------
    H : ndarray (N, N)
        The Hessian of the cost in ``U`` (without the penalty), ``2 (Gamma' Qb Gamma + Rb)`` halved: the
        cost is ``1/2 U' H U + (G_z z_0)' U``.
    G_z : ndarray (N, n_z)
        The linear term's map from ``z_0``.
    theta_U : ndarray (N, N)
        The predicted arm angles ``theta_1..N - r_theta = theta_U U + theta_z z_0``.
    theta_z : ndarray (N, n_z)
    gain : ndarray (1, n_z)
        The LQ gain of the same weights (``u = -K z``), the fallback with no plan.
    theta_max : float
        The arm's soft bound (rad).
    settings : MpcSettings
    """

    H: np.ndarray
    G_z: np.ndarray
    theta_U: np.ndarray
    theta_z: np.ndarray
    gain: np.ndarray
    theta_max: float
    settings: MpcSettings

    @property
    def horizon(self) -> int:
        """``N``."""
        return self.H.shape[0]


def build_problem(plant: LinearPlant, weights: Weights, settings: MpcSettings = MpcSettings()) -> MpcProblem:
    """Condense the MPC on the LQ design's system once: prediction matrices, Hessian, terminal cost.

    Parameters
    ----------
    plant : LinearPlant
    weights : Weights
        The stage cost (the LQ design's).
    settings : MpcSettings

    Returns
    -------
    MpcProblem
    """
    import control  # lazily: python-control imports matplotlib

    F, G, Q, R = augment(plant, weights)
    try:
        P, _, K = control.dare(F, G, Q, R)
    except (ValueError, np.linalg.LinAlgError, control.ControlArgument) as exc:
        raise DesignError(f"the MPC's terminal cost has no stabilizing Riccati solution ({exc})") from None
    return condense(F, G, Q, R, np.asarray(P), np.atleast_2d(np.asarray(K, dtype=float)), settings)


def condense(
    F: np.ndarray, G: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray, K: np.ndarray, settings: MpcSettings
) -> MpcProblem:
    """The condensed problem of ``z+ = F z + G u`` with stage cost ``Q``, ``R``, terminal ``P`` (state 0: theta)."""
    N, n = settings.horizon, F.shape[0]
    Phi = np.empty((N + 1, n, n))
    Phi[0] = np.eye(n)
    for i in range(N):
        Phi[i + 1] = F @ Phi[i]
    Gamma = np.zeros((N + 1, n, N))  # z_i = Phi_i z_0 + Gamma_i U
    for i in range(1, N + 1):
        Gamma[i, :, :i] = np.concatenate([Phi[i - 1 - j] @ G for j in range(i)], axis=1)
    weights = [Q] * N + [P]
    H = float(R[0, 0]) * np.eye(N)
    G_z = np.zeros((N, n))
    for i in range(1, N + 1):
        WG = weights[i] @ Gamma[i]
        H += Gamma[i].T @ WG
        G_z += WG.T @ Phi[i]
    H = 0.5 * (H + H.T)
    theta_max = THETA_LIMIT - settings.theta_margin
    return MpcProblem(H, G_z, Gamma[1:, 0, :].copy(), Phi[1:, 0, :].copy(), K, theta_max, settings)


@dataclass
class SolveResult:
    """One solve: the plan, its status, iterations, time and whether a constraint binds."""

    U: np.ndarray
    status: str
    iterations: int
    seconds: float
    active: bool


#: The projected Armijo search's halvings of Newton's step before a projected gradient step is taken instead.
_NEWTON_HALVINGS = 8


def solve_newton(
    H: np.ndarray,
    g: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    M: np.ndarray,
    m_lo: np.ndarray,
    m_hi: np.ndarray,
    rho: float,
    U0: np.ndarray,
    *,
    max_iterations: int = 20,
    tolerance: float = 1e-7,
    deadline: float = math.inf,
    clock=time.perf_counter,
    Hinv: np.ndarray | None = None,
) -> SolveResult:
    """Minimize ``1/2 U'HU + g'U + rho/2 |max(0, MU - m_hi)|^2 + rho/2 |max(0, m_lo - MU)|^2`` on ``lo <= U <= hi``.

    A projected Newton method (Bertsekas' two-metric projection): the variables at a bound whose
    gradient pushes outwards are held, Newton's step with the generalized Hessian on the others,
    a projected Armijo search (a projected gradient step where Newton's does not descend).
    ``Hinv``, ``H``'s inverse, saves the factorization on the ticks where nothing binds.
    ``rho/2`` times the squared excess is what a slack with penalty ``rho/2 slack^2`` leaves once
    minimized out.

    Returns
    -------
    SolveResult
        Status ``solved`` when the projected gradient is below ``tolerance``, ``max_iterations``,
        or ``timeout`` when ``clock()`` passed ``deadline`` between iterations (the best plan so
        far is returned in every case).
    """
    t0 = clock()
    U = np.clip(U0, lo, hi)
    MT = M.T
    scale = tolerance * (1.0 + float(np.max(np.abs(g))))
    lipschitz = None  # of the gradient, for a projected gradient step when Newton's does not descend

    def value_grad(U):
        y = M @ U
        over = np.maximum(y - m_hi, 0.0) - np.maximum(m_lo - y, 0.0)  # the excess, signed
        HU = H @ U
        return 0.5 * (U @ HU) + g @ U + 0.5 * rho * (over @ over), HU + g + rho * (MT @ over), over != 0.0

    val, grad, pen = value_grad(U)
    status, it = "max_iterations", 0
    for it in range(max_iterations + 1):
        held = ((U <= lo) & (grad > 0)) | ((U >= hi) & (grad < 0))
        anyheld = held.any()
        pg = np.where(held, 0.0, grad) if anyheld else grad
        if np.max(np.abs(pg)) <= scale:
            status = "solved"
            break
        if it == max_iterations:
            break
        if clock() > deadline:
            status = "timeout"
            break
        anypen = pen.any()
        if not anyheld and not anypen and Hinv is not None:  # the usual tick: nothing binds
            d = -(Hinv @ grad)
        else:
            free = ~held
            Hf = H[np.ix_(free, free)] if anyheld else H.copy()
            if anypen:
                Mp = M[pen][:, free] if anyheld else M[pen]
                Hf += rho * (Mp.T @ Mp)
            d = np.zeros_like(U)
            d[free] = -np.linalg.solve(Hf, grad[free])
        # Newton's step, else a projected gradient step (which always descends). Newton's search stops at a
        # step of 1/256: a Newton direction that needs less has crossed a kink of the penalty or a bound, and
        # halving it further cost the slowest ticks up to 45 evaluations where the gradient step takes one
        # (the same plans to 2e-14 V on a twin episode at 4 V; its slowest solve 0.90 to 0.69 ms).
        for halvings in (_NEWTON_HALVINGS, 20):
            step = 1.0
            for _ in range(halvings):  # projected Armijo search
                trial = np.clip(U + step * d, lo, hi)
                tval, tgrad, tpen = value_grad(trial)
                if tval <= val + 1e-4 * (grad @ (trial - U)) + 1e-13 * (1.0 + abs(val)):
                    break
                step *= 0.5
            else:
                if lipschitz is None:
                    lipschitz = float(np.linalg.norm(H, 2) + rho * np.linalg.norm(M, 2) ** 2)
                d = -grad / lipschitz
                continue
            break
        else:
            status = "failed"
            break
        U, val, grad, pen = trial, tval, tgrad, tpen
    active = bool(pen.any() or np.any(U <= lo) or np.any(U >= hi))
    return SolveResult(U, status, it, clock() - t0, active)


class OsqpSolver:
    """OSQP on the tick's QP with a slack per predicted step; set up once, updated and warm-started each tick.

    Variables ``[U; e]`` (``e >= 0`` the slacks), cost ``1/2 U'HU + g'U + rho/2 e'e``, constraints
    ``lo <= U <= hi``, ``MU - e <= m_hi``, ``MU + e >= m_lo``, ``e >= 0``.
    """

    def __init__(self, problem: MpcProblem) -> None:
        import osqp
        import scipy.sparse as sp

        s = problem.settings
        N = problem.horizon
        rho = s.theta_penalty
        P = sp.block_diag([sp.csc_matrix(np.triu(problem.H)), rho * sp.eye(N)], format="csc")
        M = problem.theta_U
        A = sp.vstack(
            [
                sp.hstack([sp.eye(N), sp.csc_matrix((N, N))]),
                sp.hstack([sp.csc_matrix(M), -sp.eye(N)]),
                sp.hstack([sp.csc_matrix(M), sp.eye(N)]),
                sp.hstack([sp.csc_matrix((N, N)), sp.eye(N)]),
            ],
            format="csc",
        )
        self.N = N
        big = 1e20
        self._inf = big
        self.solver = osqp.OSQP()
        self.solver.setup(
            P,
            np.zeros(2 * N),
            A,
            -big * np.ones(4 * N),
            big * np.ones(4 * N),
            verbose=False,
            warm_starting=True,
            polishing=True,
            eps_abs=s.tolerance,
            eps_rel=s.tolerance,
            max_iter=50 * s.max_iterations,
            time_limit=s.time_budget,
        )

    def solve(self, g, lo, hi, m_lo, m_hi, U0) -> SolveResult:
        """The tick's QP; ``U0`` the warm start."""
        t0 = time.perf_counter()
        N, big = self.N, self._inf
        q = np.concatenate([g, np.zeros(N)])
        lower = np.concatenate([lo, -big * np.ones(N), m_lo, np.zeros(N)])
        upper = np.concatenate([hi, m_hi, big * np.ones(N), big * np.ones(N)])
        self.solver.update(q=q, l=lower, u=upper)
        self.solver.warm_start(x=np.concatenate([U0, np.zeros(N)]))
        res = self.solver.solve(raise_error=False)
        name = str(res.info.status).lower()
        status = (
            "solved"
            if name.startswith("solved") and "inaccurate" not in name
            else "timeout"
            if "time" in name
            else "max_iterations"
            if "max" in name
            else "failed"
        )
        U = np.asarray(res.x[:N], dtype=float) if res.x is not None else np.full(N, np.nan)
        if not np.all(np.isfinite(U)):
            status, U = "failed", np.zeros(N)
        slack = np.asarray(res.x[N:]) if res.x is not None else np.zeros(N)
        active = bool(np.any(slack > 1e-6) or np.any(U <= lo + 1e-6) or np.any(U >= hi - 1e-6))
        return SolveResult(U, status, int(res.info.iter), time.perf_counter() - t0, active)


class MpcRuntime:
    """The MPC as the loop runs it: ``output`` then ``update`` each tick, and the tick's solver record.

    ``output(e_theta, e_alpha, f, r_theta)`` also takes the arm's reference: the arm's bound is on
    ``theta`` itself, and the tracking error alone does not give it.

    The controller's state is the LQ realization's (:func:`design.lq.realize`): the past tracking
    errors ``e_{k-1} .. e_{k-d}`` and the arm's integral ``w_k``, which with the tick's error give
    ``z_k = [-E_k; w_k]``. Its state update is linear (the log's ``A``, ``B`` replay it); the
    output is the QP's first input.

    With a ``disturbance``, each tick also filters the disturbances from the measurements
    (``theta = r_theta - e_theta``, ``alpha = -e_alpha``: the pendulum's reference is upright) and
    the plant input the previous tick applied (its output plus the feedforward), and records the
    estimates. With ``settings.offset_free`` the tick uses it (offset-free MPC, Pannocchia &
    Rawlings 2003; Maeder, Borrelli & Morari 2009): the prediction carries the estimate, held
    constant over the horizon as a random walk's forecast is, and the QP is solved about the
    steady state it implies (:meth:`MpcDisturbance.target_map`): the arm at its reference, the
    pendulum at ``alpha_ss`` and the plant input at ``v_ss``. In those deviations the condensed
    problem is the same (``z`` with ``alpha_ss`` taken off the pendulum's history, the inputs and
    their bounds shifted by ``v_ss - f``), so a tick costs the filter's few products more.

    Parameters
    ----------
    problem : MpcProblem
    n_delays : int
        Past samples in the plant's history.
    integral : bool
        Whether ``z`` ends with the arm's integral.
    dt : float
    clock : callable
        The clock the budget is measured on (``time.perf_counter``; a test passes its own).
    disturbance : MpcDisturbance, optional
        The disturbance model; None: none, the MPC exactly as without one.
    """

    #: The per-tick record's fields (the log's sample fields for this kind).
    TICK_FIELDS = ("solver_status", "solver_iterations", "solve_time", "constraint_active", "fallback")
    #: The fields added when the controller estimates disturbances, one per entry, ``disturbance_<entry>``:
    #: ``d_{k|k}`` (V at the plant input, or rad per tick on the angle).
    DISTURBANCE_FIELD = "disturbance"

    def __init__(
        self,
        problem: MpcProblem,
        n_delays: int,
        integral: bool,
        dt: float,
        clock=time.perf_counter,
        disturbance: MpcDisturbance | None = None,
    ) -> None:
        self.problem = problem
        self.n_delays = n_delays
        self.integral = integral
        self.dt = dt
        self.clock = clock
        self.disturbance = disturbance
        self.offset_free = disturbance is not None and problem.settings.offset_free
        if problem.settings.offset_free and disturbance is None:
            raise DesignError("offset-free MPC needs a disturbance model (qube-identify --horizon ... --disturbance)")
        if self.offset_free:
            assert disturbance is not None
            if disturbance.pole != 1.0:
                raise DesignError(
                    f"offset-free MPC needs a random-walk disturbance (pole 1); this one's pole is {disturbance.pole:g}"
                )
            self._target = disturbance.target_map()
        entries = disturbance.entries if disturbance is not None else ()
        #: The per-tick record's fields: :attr:`TICK_FIELDS`, and the disturbances' estimates with a disturbance model.
        self.tick_fields = self.TICK_FIELDS + tuple(f"{self.DISTURBANCE_FIELD}_{entry}" for entry in entries)
        self.n_fallbacks = 0
        self.n_ticks = 0
        self.tick_record: tuple[float, ...] = (0.0,) * len(self.tick_fields)
        #: The plan the last tick left: its first entry is the input that tick applied.
        self.plan: np.ndarray | None = None
        #: The last tick's disturbance estimates ``d_{k|k}``, one per entry (none without a disturbance model).
        self.estimate = np.zeros(len(entries))
        #: The last tick's prediction terms ``(theta_z z_0, r_theta, shift)``: its plan predicts the arm at
        #: ``r_theta + theta_U (plan - shift) + theta_z z_0`` (``shift``: the steady state's input, offset-free).
        self.prediction: tuple[np.ndarray, float, float] = (np.zeros(problem.horizon), 0.0, 0.0)
        self._osqp = OsqpSolver(problem) if problem.settings.solver == "osqp" else None

    def step(self):
        """Fresh ``(output, update)`` of the loop's controller interface, from zero state (one per episode)."""
        p, s = self.problem, self.problem.settings
        N, m, d = p.horizon, 2, self.n_delays
        n_z = p.G_z.shape[1]
        z = np.zeros(n_z)
        held = np.zeros(m * d)  # e_{k-1} .. e_{k-d}
        w = [0.0]
        self.plan = None
        V, rho = s.voltage_limit, s.theta_penalty
        K = p.gain[0]
        Hinv = np.linalg.inv(p.H)
        code = SOLVER_STATUS
        self.n_fallbacks = self.n_ticks = 0
        est = self.disturbance
        offset_free = self.offset_free
        if est is not None:
            rows, b = np.asarray(est.rows), np.asarray(est.input)
            L, pole = est.gain, float(est.pole)
            LG = L @ est.direction
            self.estimate = np.zeros(len(est.entries))
            history = np.zeros(m * (d + 1))  # x_k .. x_{k-d}, newest first, once update has run
            # filt: f_{k-1}; predicted: x_k's one-step prediction (None until the history is full)
            kf = {"filt": np.zeros(len(est.entries)), "predicted": None, "x": np.zeros(m), "u": 0.0, "filled": 0}
            alpha_at = slice(1, m * (d + 1), m)  # the pendulum's entries of z's history

        def output(e0: float, e1: float, f: float, r_theta: float = 0.0):
            z[0], z[1] = -e0, -e1
            z[m : m + m * d] = -held
            if self.integral:
                z[-1] = w[0]
            state = held.tolist() + ([w[0]] if self.integral else [])
            lo = np.full(N, -V - f)
            hi = np.full(N, V - f)
            shift = 0.0
            zz = z
            if est is not None:
                x = kf["x"]
                x[0], x[1] = r_theta - e0, -e1
                predicted = kf["predicted"]
                if predicted is not None:  # the filter, as identify's filter_disturbance runs it
                    prior = pole * kf["filt"]
                    kf["filt"] = prior + L @ (x - predicted) - LG @ prior
                self.estimate = dhat = pole * kf["filt"]
                if offset_free:
                    T = self._target
                    alpha_ss = T[0, 0] * r_theta + float(T[0, 1:] @ dhat)
                    shift = T[1, 0] * r_theta + float(T[1, 1:] @ dhat) - f  # the output's steady state
                    zz = z.copy()
                    zz[alpha_at] -= alpha_ss
                    lo -= shift
                    hi -= shift
            g = p.G_z @ zz
            mz = p.theta_z @ zz  # theta_i - r_theta = theta_U U + mz
            self.prediction = (mz, r_theta, shift)
            m_hi = p.theta_max - r_theta - mz
            m_lo = -p.theta_max - r_theta - mz
            U0 = np.zeros(N) if self.plan is None else np.append(self.plan[1:], self.plan[-1])
            t0 = self.clock()
            try:
                if self._osqp is not None:
                    res = self._osqp.solve(g, lo, hi, m_lo, m_hi, U0 - shift)
                else:
                    res = solve_newton(
                        p.H,
                        g,
                        lo,
                        hi,
                        p.theta_U,
                        m_lo,
                        m_hi,
                        rho,
                        U0 - shift,
                        max_iterations=s.max_iterations,
                        tolerance=s.tolerance,
                        deadline=t0 + s.time_budget,
                        clock=self.clock,
                        Hinv=Hinv,
                    )
            except Exception:  # noqa: BLE001 - a solver error must not stop the motor's commands
                res = SolveResult(np.zeros(N), "failed", 0, self.clock() - t0, False)
            seconds = self.clock() - t0
            fallback = res.status != "solved" or seconds > s.time_budget
            if fallback:
                self.n_fallbacks += 1
                if self.plan is not None:
                    u = float(np.clip(self.plan[1] if N > 1 else self.plan[0], lo[0] + shift, hi[0] + shift))
                    self.plan = U0
                else:
                    u = float(np.clip(shift - K @ zz, lo[0] + shift, hi[0] + shift))
            else:
                u = float(res.U[0] + shift)
                self.plan = res.U + shift if offset_free else res.U
            self.n_ticks += 1
            record = (
                float(code.get(res.status, 3)),
                float(res.iterations),
                seconds,
                float(res.active),
                float(fallback),
            )
            self.tick_record = record if est is None else record + tuple(self.estimate.tolist())
            if est is not None:
                kf["u"] = u + f  # the plant input this tick applies
            return u, state

        def update(e0: float, e1: float, f: float) -> None:
            if d:
                held[m:] = held[:-m]
                held[0], held[1] = e0, e1
            w[0] += self.dt * e0
            if est is not None:  # x_{k+1}'s one-step prediction, off the next tick's path
                history[m:] = history[:-m]
                history[:m] = kf["x"]
                kf["filled"] += 1
                if kf["filled"] > d:
                    kf["predicted"] = rows @ history + b * kf["u"]

        return output, update
