"""The arm's random load: reconstructed from the logs by the arm's equation, its statistics by a spectral fit.

With the rest of the physics calibrated, the arm's equation solved for the torque that
reproduces the measured arm and pendulum motion under the measured voltage leaves what no
modelled term explains (:func:`reconstruct_load`): in volts at the motor, past the dead zone,

    d = (M11 theta_ddot + M12 alpha_ddot - r1(V = 0)) / (km / Rm) - V_motor,

the accelerations and rates by central differences of the encoders smoothed by a Savitzky-Golay
filter, ``V_motor`` the commands as the motor saw them (the transport delay, the dead zone), smoothed
alike. Its slow part is the
load the twin lacks; its fast part is the differentiated encoders' noise and what the twin gets
slightly wrong at the loop's frequencies. The floor is a torque too: on the rig's logs it is 50 times
what the same reconstruction leaves on the twin's replays of them (1.5e-4 against 3e-6 V^2/Hz), so the
fitted load keeps it (:class:`~qube_koopman.sim.pendulum.load.RandomLoad`'s ``floor``, flat up to the
fitted band's edge, where the logs stop telling it apart). :func:`fit_load` fits, by the Whittle likelihood of the
episodes' periodograms below :data:`FIT_BAND` Hz, a first-order (Ornstein-Uhlenbeck) load plus a
white floor, and a random walk plus a floor for comparison:

    S(f) = 2 q^2 tau^2 / (1 + (2 pi f tau)^2) + n0        (first order)
    S(f) = 2 q^2 / (2 pi f)^2 + n0                        (random walk)

one-sided, V^2/Hz. The standard errors are the Whittle likelihood's (its Fisher information,
divided by the Hann window's equivalent noise bandwidth in bins, 1.5: neighbouring bins of a
windowed periodogram are not independent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.signal import savgol_filter, welch

from qube_koopman.core.qube import SKIP_SAMPLES
from qube_koopman.sim.pendulum import CableRelaxation, PendulumParameters, RandomLoad
from qube_koopman.sim.pendulum.physics import Coefficients
from qube_koopman.sim.pendulum.relaxation import lagged

__all__ = [
    "FIT_BAND",
    "RELAXATION_TIMES",
    "LoadFit",
    "RelaxationFit",
    "reconstruct_load",
    "reconstruct_balance",
    "fit_load",
    "fit_relaxation",
    "load_fit_check",
    "load_text",
]

#: The band (Hz) whose periodogram bins the load's fit uses: above it the reconstruction is the
#: differentiated encoders and the loop's fast dynamics, not a load.
FIT_BAND = 1.0
#: Savitzky-Golay window (samples) and order of the smoothing: flat to about 5 Hz.
_SG_WINDOW, _SG_ORDER = 51, 3
#: Equivalent noise bandwidth of the Hann window, in bins.
_HANN_ENBW = 1.5


def _smooth(x: np.ndarray) -> np.ndarray:
    """The one low-pass every signal of the reconstruction sees (encoders and voltage alike), so that a step
    of the command and the arm's answer to it cancel as they do in the equation."""
    return savgol_filter(x, _SG_WINDOW, _SG_ORDER, axis=0)


def _derivatives(y: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Rates and accelerations of the smoothed angles (central differences: exact at the frequencies fitted)."""
    rate = np.gradient(y, dt, axis=0)
    return rate, np.gradient(rate, dt, axis=0)


def reconstruct_load(
    states: np.ndarray, voltage: np.ndarray, params: PendulumParameters, dt: float, start: int = SKIP_SAMPLES
) -> np.ndarray:
    """The torque on the arm (V at the motor) that the modelled terms leave, sample by sample from ``start``.

    Parameters
    ----------
    states : ndarray (n, 2)
        Measured theta and alpha (rad); alpha's zero is taken as its mean from ``start`` (a constant
        offset hardly moves the arm's equation).
    voltage : ndarray (n,)
        The plant input (V).
    params : PendulumParameters
        The calibrated twin (its cables, Coulomb friction, dead zone, inertia). Its static friction
        (``Cs``) is left out: a torque that changes within a few hundredths of a rad/s of rest, taken
        at the smoothed encoders' speed, made the reconstruction of noise-free twin episodes with
        static friction worse, not better (RMS 0.038 V against 0.027 V without it).
    dt : float
        Sample period (s).
    start : int
        First sample used (the first second, with the derivative kick, is skipped).

    Returns
    -------
    ndarray (n - start,)
    """
    k = Coefficients.of(params)
    y = np.asarray(states, float)[start:].copy()
    y[:, 1] -= y[:, 1].mean()
    y = _smooth(y)
    d1, d2 = _derivatives(y, dt)
    theta, alpha = y[:, 0], y[:, 1]
    td, ad, tdd, add = d1[:, 0], d1[:, 1], d2[:, 0], d2[:, 1]
    s, c = np.sin(alpha), np.cos(alpha)
    inertia = (k.m11 + k.quarter * s * s) * tdd + k.m12 * c * add
    known = -k.arm_damping * td - 2.0 * k.quarter * s * c * td * ad + k.m12 * s * ad * ad
    known = known - k.arm_coulomb * np.tanh(td * k.inverse_coulomb_speed)
    if k.arm_stiffness:
        x = theta - k.arm_rest
        curve = k.cable_curvature
        known = known - k.arm_stiffness * (np.tanh(curve * x) / curve if curve else x)
    if k.tilt_x or k.tilt_y:  # a tilted base's gravity on the arm (PendulumParameters' tilt_x, tilt_y)
        balance = k.tilt_x * np.sin(theta) + k.tilt_y * np.cos(theta)
        slope = k.tilt_x * np.cos(theta) - k.tilt_y * np.sin(theta)
        known = known - k.arm_gravity * balance - k.gravity * slope * s
    return (inertia - known) / k.torque_per_volt - _motor_voltage(np.asarray(voltage, float), params, dt, start)


def _motor_voltage(u: np.ndarray, params: PendulumParameters, dt: float, start: int) -> np.ndarray:
    """What the motor saw around each sample from ``start``: the commands ``params.delay`` earlier (a fraction
    of a sample splits the sample between two), past the dead zone, averaged over the samples either side
    (a centred acceleration sees both)."""
    samples = params.delay / dt
    whole = int(math.floor(samples + 1e-12))
    fraction = max(0.0, samples - whole)
    padded = np.concatenate([np.full(whole + 2, u[0]), u])
    now = padded[2 : len(padded) - whole]  # u[k - whole]
    before = padded[1 : len(padded) - whole - 1]  # u[k - whole - 1]
    held = (1 - fraction) * now + fraction * before
    held = held - np.clip(held, -params.dead_zone, params.dead_zone)
    centred = 0.5 * (held + np.concatenate([held[:1], held[:-1]]))
    return _smooth(centred[start:])


def reconstruct_balance(
    states: np.ndarray, params: PendulumParameters, dt: float, start: int = SKIP_SAMPLES
) -> np.ndarray:
    """The pendulum encoder's zero (rad) that the pendulum's equation implies, sample by sample from ``start``:
    the measured alpha less the angle at which gravity balances the measured accelerations. A
    drifting pendulum zero (the alternative to a load on the arm) shows here."""
    k = Coefficients.of(params)
    y = np.asarray(states, float)[start:].copy()
    y[:, 1] -= y[:, 1].mean()
    y = _smooth(y)
    d1, d2 = _derivatives(y, dt)
    alpha = y[:, 1]
    td, ad, tdd, add = d1[:, 0], d1[:, 1], d2[:, 0], d2[:, 1]
    s, c = np.sin(alpha), np.cos(alpha)
    needed = k.m12 * c * tdd + k.m22 * add + k.pendulum_damping * ad - k.quarter * s * c * td * td
    return alpha - np.arcsin(np.clip(needed / k.gravity, -1.0, 1.0))


@dataclass(frozen=True)
class LoadFit:
    """A fitted load (:func:`fit_load`).

    Attributes
    ----------
    load : RandomLoad
        The first-order load (or the random walk, when its likelihood is higher).
    standard_errors : dict
        ``diffusion`` and ``time_constant`` (V/sqrt(s), s); ``time_constant`` absent for a random walk.
    floor : float
        The white floor (V^2/Hz) fitted beside it.
    log_likelihood : dict
        Whittle log-likelihood of ``"first-order"`` and ``"random-walk"`` (each with its floor).
    n_bins : int
        Periodogram bins used (over all episodes).
    slow_std : float
        Root mean square over the episodes of the reconstruction's standard deviation below 0.3 Hz (V).
    """

    load: RandomLoad
    standard_errors: dict
    floor: float
    log_likelihood: dict
    n_bins: int
    slow_std: float


def _periodograms(loads: Sequence[np.ndarray], dt: float, band: float):
    """Frequencies and Hann-windowed periodograms (one-sided, V^2/Hz) of the bins in (0, band], stacked."""
    fs, ps = [], []
    for d in loads:
        f, p = welch(np.asarray(d, float), fs=1.0 / dt, nperseg=len(d), window="hann", detrend="constant")
        keep = (f > 0) & (f <= band)
        fs.append(f[keep])
        ps.append(p[keep])
    return np.concatenate(fs), np.concatenate(ps)


def _psd(f: np.ndarray, q: float, tau: float, floor: float) -> np.ndarray:
    """The module docstring's one-sided spectrum (V^2/Hz): first order, or a random walk where ``tau`` is inf."""
    w = 2 * np.pi * f
    if math.isinf(tau):
        return 2 * q * q / w**2 + floor
    return 2 * q * q * tau**2 / (1 + (w * tau) ** 2) + floor


def _spectrum(z: np.ndarray, f: np.ndarray, walk: bool) -> np.ndarray:
    """:func:`_psd` in the fitted variables: ``log q, log n`` (a walk) or ``log q, log tau, log n``."""
    if walk:
        log_q, log_n = z
        return _psd(f, np.exp(log_q), math.inf, np.exp(log_n))
    log_q, log_tau, log_n = z
    return _psd(f, np.exp(log_q), np.exp(log_tau), np.exp(log_n))


def _whittle(f: np.ndarray, p: np.ndarray, walk: bool, z0: np.ndarray):
    def cost(z):
        s = _spectrum(z, f, walk)
        return float(np.sum(np.log(s) + p / s))

    best = minimize(cost, z0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 4000})
    best = minimize(cost, best.x, method="BFGS")
    # Fisher information of the Whittle likelihood: sum of the gradients of log S, by differences.
    grads = []
    for i in range(len(best.x)):
        step = np.zeros_like(best.x)
        step[i] = 1e-5
        grads.append((np.log(_spectrum(best.x + step, f, walk)) - np.log(_spectrum(best.x - step, f, walk))) / 2e-5)
    g = np.array(grads)
    info = g @ g.T / _HANN_ENBW
    return best.x, -best.fun, np.linalg.pinv(info)  # pinv: a floor fitted to nothing leaves a flat direction


def fit_load(loads: Sequence[np.ndarray], dt: float, band: float = FIT_BAND) -> LoadFit:
    """Fit the statistics of a random load to reconstructed loads (:func:`reconstruct_load`), one per episode.

    Parameters
    ----------
    loads : sequence of ndarray
        Each episode's reconstruction (V).
    dt : float
        Sample period (s).
    band : float
        Highest frequency (Hz) fitted.

    Returns
    -------
    LoadFit
    """
    from scipy.signal import butter, sosfiltfilt

    f, p = _periodograms(loads, dt, band)
    if f.size < 4:
        raise ValueError(f"{f.size} periodogram bins below {band:g} Hz: the logs are too short to fit a load")
    level = float(np.median(p))
    z_ou, ll_ou, cov_ou = _whittle(f, p, False, np.array([0.5 * math.log(level), 0.0, math.log(level / 4)]))
    z_rw, ll_rw, cov_rw = _whittle(f, p, True, np.array([0.5 * math.log(level), math.log(level / 4)]))
    sos = butter(2, 0.3, fs=1.0 / dt, output="sos")
    slow = math.sqrt(float(np.mean([np.var(sosfiltfilt(sos, np.asarray(d, float))) for d in loads])))
    likelihood = {"first-order": ll_ou, "random-walk": ll_rw}
    if ll_rw > ll_ou + 1e-9 * abs(ll_ou):  # the walk explains the bins better (a tie: no load either way)
        q = math.exp(z_rw[0])
        floor = math.exp(z_rw[1])
        errors = {"diffusion": q * math.sqrt(cov_rw[0, 0]), "floor": floor * math.sqrt(cov_rw[1, 1])}
        return LoadFit(RandomLoad(q, floor=floor, floor_corner=band), errors, floor, likelihood, f.size, slow)
    q, tau, floor = (math.exp(v) for v in z_ou)
    errors = {
        "diffusion": q * math.sqrt(cov_ou[0, 0]),
        "time_constant": tau * math.sqrt(cov_ou[1, 1]),
        "floor": floor * math.sqrt(cov_ou[2, 2]),
    }
    return LoadFit(RandomLoad(q, tau, floor, band), errors, floor, likelihood, f.size, slow)


#: The relaxation times (s) :func:`fit_relaxation` tries: a second's lag, a decade either way.
RELAXATION_TIMES = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: The low passes (s) of the excitation that :func:`fit_relaxation` takes as instruments, beside it as it is.
INSTRUMENT_LAGS = (0.1, 0.3, 1.0, 3.0, 10.0)


@dataclass(frozen=True)
class RelaxationFit:
    """What :func:`fit_relaxation` found.

    Attributes
    ----------
    relaxation : CableRelaxation
        The cables' relaxation, at the relaxation time that left the least.
    residuals : list of ndarray
        Each episode's load with the relaxation's torque taken out (V): what is left for the random load.
    explained : float
        The share of the loads' variance below :data:`FIT_BAND` Hz (each episode's mean removed)
        that the relaxation's torque explains.
    explained_by_time : dict of float to float
        At every relaxation time tried, the share of the loads' excitation-driven part (below) that
        its fit explains: the criterion the relaxation time is chosen by.
    driven : float
        The share of the loads' slow variance that a linear filter of the excitation explains at
        all: torque the excitation causes, which no disturbance from outside the loop can be.
    standard_errors : dict of str to float
        ``fast`` and ``relaxing``'s standard errors (V/rad) at the chosen relaxation time, from the
        spread of the fit over :data:`RELAXATION_BOOTSTRAP` resamplings of the episodes (whole
        episodes, so that each one's slow wander counts once; NaN with a single episode).
    """

    relaxation: CableRelaxation
    residuals: list
    explained: float
    explained_by_time: dict
    driven: float
    standard_errors: dict = field(default_factory=dict)


#: Resamplings of the episodes behind :attr:`RelaxationFit.standard_errors` (seeded: a fit is reproducible).
RELAXATION_BOOTSTRAP = 400


def fit_relaxation(
    loads: Sequence[np.ndarray],
    thetas: Sequence[np.ndarray],
    excitations: Sequence[np.ndarray],
    dt: float,
    time_constants: Sequence[float] = RELAXATION_TIMES,
    band: float = FIT_BAND,
) -> RelaxationFit:
    """The part of reconstructed loads that the arm's motion drives, as the cables' relaxation.

    The load is regressed on the arm angle ``theta`` and the relaxing element's memory of it ``x``
    (:meth:`~qube_koopman.sim.pendulum.relaxation.CableRelaxation.remembered`), all low-passed below
    ``band`` Hz (zero-phase Butterworth, order 4: above it the reconstruction is the differentiated
    encoders' noise), each episode's mean removed. In closed loop a disturbance from outside moves
    the arm too, so plain least squares can credit the arm with it (on twin episodes whose arm only
    a random load and a fast random feedforward moved, it found 0.6 V/rad of stiffness where there
    was none; on replays of the soft controller's logs, whose references move the arm slowly, it
    did not, and on the logs themselves the two agree within 6 %). The fit is therefore
    two-stage least squares with the excitation as the instrument:
    ``theta`` and ``x`` are replaced by what a linear filter of the excitation (each channel
    low-passed over :data:`INSTRUMENT_LAGS` seconds, and as it is) predicts of them, which no
    disturbance moves. At each of ``time_constants`` the fit is made, and the time whose predicted
    torque leaves least of the loads' excitation-driven part is kept. Where ``x``'s coefficient
    comes out negative (no element that gives way) ``theta`` alone is fitted: a stiffness, no
    relaxation.

    Parameters
    ----------
    loads : sequence of ndarray
        Each episode's reconstruction (:func:`reconstruct_load`, V).
    thetas : sequence of ndarray
        The measured arm angle over the same samples (rad).
    excitations : sequence of ndarray
        What drives each episode from outside the loop over the same samples, (n,) or (n, m): the
        arm's reference, the feedforward.
    dt : float
        Sample period (s).
    time_constants : sequence of float
        Relaxation times tried (s).
    band : float
        Highest frequency (Hz) fitted.

    Returns
    -------
    RelaxationFit
    """
    from scipy.signal import butter, sosfiltfilt

    loads = [np.asarray(d, dtype=float) for d in loads]
    thetas = [np.asarray(t, dtype=float) for t in thetas]
    excitations = [np.asarray(e, dtype=float).reshape(len(e), -1) for e in excitations]
    if not loads or not len(loads) == len(thetas) == len(excitations):
        raise ValueError("give one arm angle and one excitation sequence per load")
    if any(d.ndim != 1 or t.shape != d.shape or len(e) != len(d) for d, t, e in zip(loads, thetas, excitations)):
        raise ValueError("each arm angle and excitation must have its load's length")
    if not time_constants:
        raise ValueError("give at least one relaxation time")
    sos = butter(4, band, fs=1.0 / dt, output="sos")

    def slow(x: np.ndarray) -> np.ndarray:
        return sosfiltfilt(sos, x - x.mean(axis=0), axis=0)

    def instruments(e: np.ndarray) -> np.ndarray:  # the excitation and its low passes
        return slow(np.column_stack([e] + [lagged(e, lag, dt) for lag in INSTRUMENT_LAGS]))

    y = np.concatenate([slow(d) for d in loads])
    z = np.vstack([instruments(e) for e in excitations])
    z = z[:, np.std(z, axis=0) > 0]  # a channel that never moves instruments nothing
    theta_slow = np.concatenate([slow(t) for t in thetas])
    driven = z @ np.linalg.lstsq(z, y, rcond=None)[0]  # the loads' part the excitation explains
    best: tuple[float, CableRelaxation] | None = None
    by_time: dict[float, float] = {}
    for tau in time_constants:
        x_slow = np.concatenate([slow(lagged(t, float(tau), dt)) for t in thetas])
        regressors = np.column_stack([x_slow, theta_slow])
        predicted = z @ np.linalg.lstsq(z, regressors, rcond=None)[0]  # first stage
        (relaxing, theta_coef), *_ = np.linalg.lstsq(predicted, y, rcond=None)
        if relaxing < 0:
            relaxing, theta_coef = 0.0, float(predicted[:, 1] @ y / (predicted[:, 1] @ predicted[:, 1]))
        by_time[float(tau)] = _share(driven, relaxing * predicted[:, 0] + theta_coef * predicted[:, 1])
        if best is None or by_time[float(tau)] > best[0]:
            best = (by_time[float(tau)], CableRelaxation(float(-theta_coef), float(relaxing), float(tau)))
    assert best is not None  # at least one time was tried
    relaxation = best[1]
    residuals = [d - relaxation.torque(t, relaxation.remembered(t, dt)) for d, t in zip(loads, thetas)]
    torque = np.concatenate([slow(d - r) for d, r in zip(loads, residuals)])
    x_slow = np.concatenate([slow(lagged(t, relaxation.time_constant, dt)) for t in thetas])
    errors = _bootstrap_errors(
        [len(d) for d in loads], z, np.column_stack([x_slow, theta_slow]), y, RELAXATION_BOOTSTRAP
    )
    return RelaxationFit(relaxation, residuals, _share(y, torque), by_time, _share(y, driven), errors)


def relaxation_signals(episode) -> tuple[np.ndarray, np.ndarray]:
    """An episode's arm angle and excitation (the arm's reference, the feedforward; (n, 2)) over the samples of
    its :func:`reconstruct_load`: what :func:`fit_relaxation` takes beside its load."""
    theta = np.asarray(episode.states, float)[SKIP_SAMPLES:, 0]
    excitation = np.column_stack(
        [np.asarray(episode.references, float)[SKIP_SAMPLES:, 0], np.asarray(episode.feedforward, float)[SKIP_SAMPLES:]]
    )
    return theta, excitation


def _two_stage(zz: np.ndarray, zr: np.ndarray, zy: np.ndarray) -> tuple[float, float]:
    """``(relaxing, theta's coefficient)`` of two-stage least squares from the moments ``Z'Z``, ``Z'R``, ``Z'y``
    (``R``: the element's memory and the arm angle), as :func:`fit_relaxation` makes it (the arm alone where the
    relaxing part comes out negative)."""
    first = np.linalg.lstsq(zz, zr, rcond=None)[0]  # the first stage's coefficients
    pp, py = first.T @ zz @ first, first.T @ zy  # P'P and P'y for the predicted regressors P = Z first
    relaxing, theta_coef = np.linalg.lstsq(pp, py, rcond=None)[0]
    if relaxing < 0:
        return 0.0, float(py[1] / pp[1, 1])
    return float(relaxing), float(theta_coef)


def _bootstrap_errors(lengths: list[int], z: np.ndarray, regressors: np.ndarray, y: np.ndarray, n: int) -> dict:
    """``fast`` and ``relaxing``'s standard errors: the spread of the two-stage fit over ``n`` resamplings of
    whole episodes (``lengths``: each one's rows), from each episode's moments (a resampling sums them, so
    it costs a few small solves, not a regression over every sample)."""
    if len(lengths) < 2:
        return {"fast": float("nan"), "relaxing": float("nan")}
    edges = np.cumsum([0, *lengths])
    parts = [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
    zz = np.stack([z[k].T @ z[k] for k in parts])
    zr = np.stack([z[k].T @ regressors[k] for k in parts])
    zy = np.stack([z[k].T @ y[k] for k in parts])
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(n):
        counts = np.bincount(rng.integers(0, len(parts), len(parts)), minlength=len(parts)).astype(float)
        draws.append(_two_stage(*(np.tensordot(counts, m, axes=1) for m in (zz, zr, zy))))
    relaxing, theta_coef = np.array(draws).T
    return {"fast": float(np.std(-theta_coef, ddof=1)), "relaxing": float(np.std(relaxing, ddof=1))}


def _share(y: np.ndarray, fit: np.ndarray) -> float:
    """The share of ``y``'s sum of squares that ``fit`` explains (0 for a ``y`` of zeros)."""
    total = float(y @ y)
    return 1.0 - float((y - fit) @ (y - fit)) / total if total > 0 else 0.0


#: The bands (Hz) :func:`load_fit_check` compares the fitted spectrum with the data in.
CHECK_BANDS = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.6), (0.6, 1.0))


def load_fit_check(
    loads: Sequence[np.ndarray], dt: float, bands: Sequence[tuple[float, float]] = CHECK_BANDS
) -> list[tuple[str, float]]:
    """How well :func:`fit_load`'s spectrum follows the reconstructions, band by band.

    Fits the load to ``loads`` as :func:`fit_load` does, then divides the periodograms' mean power
    in each band by the fitted spectrum's (load and floor) over the same bins: 1 where the fitted
    process has the data's power there. Bands without a bin are left out.

    Returns
    -------
    list of (str, float)
        ``("LO-HI Hz", ratio)`` per band.
    """
    fit = fit_load(loads, dt)
    load = fit.load
    f, p = _periodograms(loads, dt, max(hi for _, hi in bands))
    model = _psd(f, load.diffusion, load.time_constant, fit.floor)
    out = []
    for lo, hi in bands:
        k = (f > lo) & (f <= hi)
        if k.any():
            out.append((f"{lo:g}-{hi:g} Hz", float(p[k].mean() / model[k].mean())))
    return out


def load_text(fits: dict) -> str:
    """The fitted loads as the report's markdown: one row per group of logs (all of them, each recording day)."""
    lines = [
        "## The arm's random load",
        "",
        "The arm's equation run backwards on the fitted logs leaves a slow torque (V at the motor); its",
        f"periodograms below {FIT_BAND:g} Hz fitted by the Whittle likelihood (first-order load + white floor, and a",
        "random walk + floor for comparison):",
        "",
        "| logs | kind | diffusion q (V/sqrt(s)) | time constant (s) | std (V) | floor (V^2/Hz) "
        "| slow std < 0.3 Hz (V) | log-lik first-order - walk |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, fit in fits.items():
        se = fit.standard_errors
        tau = (
            "inf"
            if fit.load.kind == "random-walk"
            else f"{fit.load.time_constant:.3g} +- {se.get('time_constant', float('nan')):.2g}"
        )
        std = "-" if fit.load.kind == "random-walk" else f"{fit.load.std:.4f}"
        gain = fit.log_likelihood["first-order"] - fit.log_likelihood["random-walk"]
        lines.append(
            f"| {label} | {fit.load.kind} | {fit.load.diffusion:.4f} +- {se['diffusion']:.2g} | {tau} | {std} "
            f"| {fit.floor:.2e} | {fit.slow_std:.4f} | {gain:+.1f} |"
        )
    return "\n".join(lines) + "\n"
