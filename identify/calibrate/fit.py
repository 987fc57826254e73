"""Grey-box calibration of the simulator's pendulum by multiple-shooting least squares."""

from __future__ import annotations

import sys
from dataclasses import asdict, replace
from typing import Mapping, Sequence

import numpy as np
from scipy.signal import savgol_filter
from scipy.sparse.linalg import splu

from qube_koopman.identify.calibrate import shooting as ms
from qube_koopman.identify.calibrate.solver import levenberg_marquardt
from qube_koopman.sim.pendulum import PendulumParameters

__all__ = ["HoldRefused", "PlantCalibration"]

#: Standard deviation (rad) of a 2048-count encoder's quantization error: the residual scale.
ENCODER_SIGMA = 2 * np.pi / 2048 / np.sqrt(12)


class HoldRefused(ValueError):
    """Refused: :class:`PlantCalibration`'s ``hold`` names a parameter it cannot keep at the value given.

    Attributes
    ----------
    per_setup : bool
        The parameter has a value per setup in this fit (fitting one value for all setups could hold it).
    """

    def __init__(self, message: str, per_setup: bool = False) -> None:
        super().__init__(message)
        self.per_setup = per_setup


class _Progress:
    """A one-line progress bar on stderr (iterations of the solver, best cost so far)."""

    def __init__(self, enabled: bool, budget: int) -> None:
        self.enabled, self.budget = enabled and sys.stderr.isatty(), budget

    def __call__(self, iteration: int, cost: float) -> None:
        if self.enabled:
            filled = min(30, 30 * iteration // self.budget)
            print(
                f"\rcalibrating [{'#' * filled}{'.' * (30 - filled)}] iteration {iteration}/{self.budget}, "
                f"cost {cost:.5g}",
                end="",
                file=sys.stderr,
                flush=True,
            )

    def done(self) -> None:
        if self.enabled:
            print(file=sys.stderr, flush=True)


class PlantCalibration:
    """Fit the pendulum's physical parameters and per-episode encoder offsets to logs.

    Parameters
    ----------
    horizon : float
        Shooting segment length (s).
    skip : float
        Seconds dropped at each episode's start (the hand-raising and derivative kick).
    delay : int
        Transport delay in whole samples assumed between the logged voltage and the motor.
    nominal : PendulumParameters or None
        Starting point; the parameters not fitted keep these values. Default:
        :meth:`PendulumParameters.previous` (the workbook with hardware-fitted
        damping), so a calibration does not start from an earlier one.
    stride : float or None
        Seconds between segment starts (default: ``2 * horizon``, every other stretch of data).
    max_nfev : int
        Iteration budget of the solver (Levenberg-Marquardt iterations).
    progress : bool
        Show a progress line on stderr.
    weighting : {"episode", "group"}
        With ``groups`` given to :meth:`fit` (for example each episode's
        controller): ``"episode"`` counts every episode alike, ``"group"``
        weights the residuals so that every group counts alike however many
        episodes it has (each group's squared residuals sum to the same share).
    jacobian : {"tangents", "differences"}
        How the solver's Jacobian is computed: the simulation's forward sensitivities, every
        parameter and segment start along one simulation (the default), or forward differences,
        a simulation per parameter (the way it was computed before; the two agree to the
        differences' rounding, about 1e-6 of a column, and the fits to a thousandth of a
        standard error).
    hold : dict of str to float, optional
        Physical parameters of :data:`~qube_koopman.identify.calibrate.shooting.PHYSICAL_NAMES` held
        at a value of their own rather than fitted (for example ``{"cable_softening": 0.0}``, a
        linear cable spring), each within its physical range; the others are fitted around it, and
        their standard errors are conditional on it (a held parameter's is 0). A parameter with a
        value per setup may not be held.

    Attributes
    ----------
    params_ : PendulumParameters
    nominal_ : PendulumParameters
        The starting point used (``nominal`` or its default).
    standard_errors_ : dict of str to float
        Of the fitted physical parameters (asymptotic, from the Jacobian).
    correlation_ : ndarray (n_fitted, n_fitted)
    fitted_names_ : list of str
    setup_values_ : dict of str to dict of str to float
        With ``setups`` given to :meth:`fit`: per setup parameter (``Kr``, ``delay``), its value
        fitted for each of its setups (labels), the rest of the physics shared;
        ``setup_errors_`` their standard errors. ``params_`` then holds, for such a
        parameter, the median over its setups (of the logarithms for the stiffness, a scale):
        the central guess for a setup no log shows. Empty without setups.
    alpha_offsets_ : ndarray (n_episodes,)
        Pendulum encoder zero offsets (rad); ``alpha_offset_errors_`` their standard errors.
    residual_rms_ : ndarray (n_episodes, 2)
        RMS prediction error (rad) of theta and alpha over each episode's segments.
    held_ : dict of str to float
        The parameters ``hold`` held, at their values (empty without ``hold``).
    warnings_ : list of str
        Parameters at a bound or poorly identified.
    cost_, nfev_, njev_ : float, int, int
        The final cost (half the weighted sum of squares), the residual evaluations and the Jacobians
        computed (the solver reuses a Jacobian for a step its linear model predicted well:
        :mod:`~qube_koopman.identify.calibrate.solver`).
    """

    def __init__(
        self,
        horizon: float = 0.2,
        skip: float = 1.0,
        delay: int = 0,
        nominal: PendulumParameters | None = None,
        stride: float | None = None,
        max_nfev: int = 40,
        progress: bool = False,
        weighting: str = "episode",
        jacobian: str = "tangents",
        hold: Mapping[str, float] | None = None,
    ) -> None:
        self.horizon = horizon
        self.skip = skip
        self.delay = delay
        self.nominal = nominal
        self.stride = stride
        self.max_nfev = max_nfev
        self.progress = progress
        self.weighting = weighting
        self.jacobian = jacobian
        self.hold = hold

    def fit(
        self,
        measured: Sequence[np.ndarray],
        voltages: Sequence[np.ndarray],
        dt: float,
        groups: Sequence | None = None,
        setups: Mapping[str, Sequence] | None = None,
        fixed: Mapping[str, Sequence[float]] | None = None,
        loads: Sequence[np.ndarray] | None = None,
    ) -> "PlantCalibration":
        """Fit to episodes: ``measured[i]`` (n_i, 2) angles, ``voltages[i]`` (n_i,) plant input (V).

        ``groups``: a label per episode (for example its controller), used by ``weighting="group"``.
        ``setups``: per parameter of :data:`~qube_koopman.identify.calibrate.shooting.SETUP_PARAMETERS`,
        a label per episode (the cables' stiffness ``Kr``: its recording day; the ``delay``: its
        session): each setup gets its own value, the rest of the physics is shared
        (:attr:`setup_values_`). ``fixed``: per parameter of
        :data:`~qube_koopman.identify.calibrate.shooting.FIXED_PARAMETERS`, a value per episode that
        its segments simulate with and the fit leaves as given (the base's tilt of the episode's day,
        :func:`~qube_koopman.identify.calibrate.tilt_fit.fit_tilt`). ``loads``: per episode, a known
        torque on the arm at each sample (n_i,), in volts at the motor past the dead zone, that every
        segment simulates with (the cables' relaxation computed from the logged arm angle:
        :meth:`~qube_koopman.sim.pendulum.relaxation.CableRelaxation.torque_of`).
        """
        if len(measured) != len(voltages) or not measured:
            raise ValueError("need one voltage sequence per measured episode, and at least one episode")
        if loads is not None:
            loads = [np.asarray(d, float) for d in loads]
            if len(loads) != len(voltages) or any(d.shape != np.shape(u) for d, u in zip(loads, voltages)):
                raise ValueError("need one load per episode, as long as its voltages")
        if self.weighting not in ("episode", "group"):
            raise ValueError(f"weighting must be 'episode' or 'group', got {self.weighting!r}")
        if self.jacobian not in ("tangents", "differences"):
            raise ValueError(f"jacobian must be 'tangents' or 'differences', got {self.jacobian!r}")
        setups = dict(setups or {})
        unknown = sorted(set(setups) - set(ms.SETUP_PARAMETERS))
        if unknown:
            may = ", ".join(ms.SETUP_PARAMETERS)
            raise ValueError(f"no setup may have its own {', '.join(unknown)}; these may: {may}")
        held = {name: np.asarray(values, float) for name, values in (fixed or {}).items()}
        unfit = sorted(set(held) - set(ms.FIXED_PARAMETERS))
        if unfit:
            raise ValueError(
                f"no fixed {', '.join(unfit)}: these may be held per episode: {', '.join(ms.FIXED_PARAMETERS)}"
            )
        for name, labels in (
            ("group", groups),
            *((f"{k} setup", v) for k, v in setups.items()),
            *((f"fixed {k}", v) for k, v in held.items()),
        ):
            if labels is not None and len(labels) != len(measured):
                raise ValueError(
                    f"need one {name} label per episode: {len(labels)} labels for {len(measured)} episodes"
                )
        hold = self._checked_hold(setups)
        h = max(2, int(round(self.horizon / dt)))
        seg = ms.make_segments(
            [np.asarray(y, float) for y in measured],
            [np.asarray(u, float) for u in voltages],
            h,
            int(round(self.skip / dt)),
            self.delay,
            2 * h if self.stride is None else max(1, int(round(self.stride / dt))),
            loads,
        )
        n_ep = len(measured)
        if self.weighting == "group" and groups is not None:
            seg = replace(seg, weight=_group_weights(seg.episode, groups))
        if held:
            seg = replace(seg, fixed={name: values[seg.episode] for name, values in held.items()})
        distinct = {name: sorted({str(v) for v in labels}) for name, labels in setups.items()}
        self.setup_labels_ = {name: labels for name, labels in distinct.items() if len(labels) > 1}
        if self.setup_labels_:
            index = {name: {label: i for i, label in enumerate(labels)} for name, labels in self.setup_labels_.items()}
            seg = replace(
                seg,
                setups={
                    name: np.array([index[name][str(setups[name][e])] for e in seg.episode])
                    for name in ms.SETUP_PARAMETERS
                    if name in index
                },
            )
        self.nominal_ = PendulumParameters.previous() if self.nominal is None else self.nominal
        z0 = self._start(measured, seg, n_ep, dt)
        lo, hi = self._bounds(n_ep, seg.n, seg)
        for i, z_held in hold.items():  # a held variable: both bounds at its value, which the solver keeps
            lo[i] = hi[i] = z0[i] = z_held
        z0 = np.clip(z0, lo, hi)
        progress = _Progress(self.progress, self.max_nfev)

        def fun(z):
            return ms.residuals(z, seg, n_ep, self.nominal_, dt, ENCODER_SIGMA)

        def jac(z, r):
            return ms.jacobian(z, r, seg, n_ep, self.nominal_, dt, ENCODER_SIGMA, method=self.jacobian)

        def normal(J):
            return ms.normal_matrix(J, seg, n_ep)

        result = levenberg_marquardt(fun, jac, z0, lo, hi, max_iter=self.max_nfev, callback=progress, normal=normal)
        progress.done()
        self._store(result, seg, n_ep, lo, hi, sorted(hold))
        return self

    def _checked_hold(self, setups: Mapping) -> dict[int, float]:
        """``hold`` as {index of the physical variable: its fitted variable's value}, checked."""
        out = {}
        for name, value in dict(self.hold or {}).items():
            if name not in ms.PHYSICAL_NAMES:
                raise HoldRefused(f"cannot hold {name!r}: the fitted parameters are {', '.join(ms.PHYSICAL_NAMES)}")
            if len({str(label) for label in setups.get(name, ())}) > 1:
                raise HoldRefused(f"cannot hold {name}: it has a value per setup in this fit", per_setup=True)
            i = ms.PHYSICAL_NAMES.index(name)
            nominal = PendulumParameters.previous() if self.nominal is None else self.nominal
            low, high = (getattr(ms.to_params(bound, nominal), name) for bound in ms.physical_bounds())
            if not low <= float(value) <= high:
                raise HoldRefused(f"cannot hold {name} at {value:g}: its physical range is [{low:.4g}, {high:.4g}]")
            out[i] = float(ms.from_params(replace(nominal, **{name: float(value)}), nominal)[i])
        return out

    def _start(self, measured, seg: ms.Segments, n_ep: int, dt: float) -> np.ndarray:
        """Nominal parameters, offsets = mean measured alpha, nodes from smoothed data."""
        offsets = np.array(
            [np.mean(np.asarray(y)[seg.start[seg.episode == e].min() :, 1]) for e, y in enumerate(measured)]
        )
        rates = [savgol_filter(np.asarray(y, float), 21, 2, deriv=1, delta=dt, axis=0) for y in measured]
        nodes = np.empty((seg.n, 4))
        nodes[:, :2] = seg.y[0]
        nodes[:, 1] -= offsets[seg.episode]
        nodes[:, 2:] = np.stack([rates[e][k] for e, k in zip(seg.episode, seg.start)]) / ms.RATE_SCALE
        phys = ms.from_params(self.nominal_, self.nominal_)
        setups = [phys[ms.PHYSICAL_NAMES.index(name)] for name, _ in ms.setup_variables(seg)]  # from the nominal
        return np.concatenate([phys, setups, offsets / ms.OFFSET_SCALE, nodes.ravel()])

    @staticmethod
    def _bounds(n_ep: int, n_seg: int, seg: ms.Segments | None = None) -> tuple[np.ndarray, np.ndarray]:
        plo, phi = ms.physical_bounds(seg)
        lo = np.concatenate([plo, np.full(n_ep, -100.0), np.full(4 * n_seg, -np.inf)])
        hi = np.concatenate([phi, np.full(n_ep, 100.0), np.full(4 * n_seg, np.inf)])
        return lo, hi

    def _store(
        self, result, seg: ms.Segments, n_ep: int, lo: np.ndarray, hi: np.ndarray, held: Sequence[int] = ()
    ) -> None:
        z = result.x
        n_x = ms.n_setup_variables(seg)
        n_phys = ms.N_PHYSICAL + n_x
        phys, offsets, _ = ms.unpack(z, n_ep, seg.n, n_x)
        self.params_ = ms.to_params(phys, self.nominal_)
        self.cost_, self.nfev_, self.njev_ = float(result.cost), int(result.nfev), int(result.njev)
        self.converged_ = bool(result.converged)
        n_res, n_var = result.jac.shape
        s2 = 2 * result.cost / max(1, n_res - n_var)
        cov = _marginal_covariance(ms.normal_matrix(result.jac, seg, n_ep), n_phys + n_ep, held) * s2
        z_se = np.sqrt(np.maximum(np.diag(cov), 0))
        self.setup_values_: dict[str, dict[str, float]] = {}
        self.setup_errors_: dict[str, dict[str, float]] = {}
        if n_x:
            self._central_setups(phys, z_se, cov, seg)
        self.fitted_names_ = [p[0] for p in ms.PHYSICAL]
        self.standard_errors_ = {}
        for i, (name, kind, scale, _, _) in enumerate(ms.PHYSICAL):
            value = getattr(self.params_, name)
            self.standard_errors_[name] = float(abs(value) * z_se[i] if kind == "log" else scale * z_se[i])
        d = np.sqrt(np.maximum(np.diag(cov)[: ms.N_PHYSICAL], 1e-300))
        self.correlation_ = cov[: ms.N_PHYSICAL, : ms.N_PHYSICAL] / np.outer(d, d)
        self.alpha_offsets_ = offsets
        self.alpha_offset_errors_ = ms.OFFSET_SCALE * z_se[n_phys:]
        r = result.fun.reshape(seg.n, seg.horizon + 1, 2) * ENCODER_SIGMA
        if seg.weight is not None:  # the residuals as measured, not as weighted
            r = r / seg.weight[:, None, None]
        self.residual_rms_ = np.array([np.sqrt(np.mean(r[seg.episode == e] ** 2, axis=(0, 1))) for e in range(n_ep)])
        self.held_ = {ms.PHYSICAL_NAMES[i]: float(getattr(self.params_, ms.PHYSICAL_NAMES[i])) for i in held}
        self.warnings_ = self._warnings(z[: ms.N_PHYSICAL], lo, hi)

    def _central_setups(self, phys: np.ndarray, z_se: np.ndarray, cov: np.ndarray, seg: ms.Segments) -> None:
        """Each setup's values and errors (:attr:`setup_values_`), and the central ones into ``params_``.

        Median over the setups (of the logarithms for a scale, the stiffness), so a setup far off
        does not drag the guess for one no log shows; its standard error is the median setup's,
        or for an even count the delta method's of the mean of the two middle ones (their estimates
        nearly independent). Written into ``z_se`` at the parameter's physical variable.
        """
        values = ms.setup_values(phys, seg)
        errors = ms.setup_values(z_se[: len(phys)], seg)  # the same (linear) scale maps the errors
        extra = {key: ms.N_PHYSICAL + j for j, key in enumerate(ms.setup_variables(seg))}
        central = {}
        for name, v in values.items():
            i = ms.PHYSICAL_NAMES.index(name)
            labels = self.setup_labels_[name]
            self.setup_values_[name] = dict(zip(labels, v.tolist()))
            self.setup_errors_[name] = dict(zip(labels, errors[name].tolist()))
            log = name == "Kr"
            key = np.log(np.maximum(v, 1e-300)) if log else v
            order = np.argsort(key, kind="stable")
            middle = order[(len(v) - 1) // 2 : len(v) // 2 + 1]  # one, or the two middle setups
            variables = [i if s == 0 else extra[name, int(s)] for s in middle]
            c = cov[np.ix_(variables, variables)] * ms.PHYSICAL[i][2] ** 2
            if log:
                c = c / np.outer(v[middle], v[middle])
            spread = np.sqrt(max(float(np.sum(c)), 0.0)) / len(middle)
            central[name] = float(np.exp(np.mean(key[middle])) if log else np.mean(v[middle]))
            z_se[i] = (central[name] * spread if log else spread) / ms.PHYSICAL[i][2]
        self.params_ = replace(self.params_, **central)

    def _warnings(self, z: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list[str]:
        out = []
        for i, name in enumerate(self.fitted_names_):
            if name in self.held_:
                continue
            span = hi[i] - lo[i]
            value, se = getattr(self.params_, name), self.standard_errors_[name]
            if z[i] - lo[i] < 1e-4 * span or hi[i] - z[i] < 1e-4 * span:
                out.append(f"{name} is at a bound of its physical range ({value:.4g})")
            elif se > 0.5 * abs(value):
                out.append(f"{name} is poorly identified (standard error {se:.2g} vs value {value:.2g})")
        n = len(self.fitted_names_)
        for i in range(n):
            for j in range(i + 1, n):
                if abs(self.correlation_[i, j]) > 0.95:  # (a held parameter's correlations are 0)
                    out.append(
                        f"{self.fitted_names_[i]} and {self.fitted_names_[j]} are strongly correlated "
                        f"({self.correlation_[i, j]:+.3f}): only a combination of them is well identified"
                    )
        return out

    def summary(self) -> dict:
        """Plain data for reports and provenance."""
        return {
            "params": asdict(self.params_),
            "standard_errors": dict(self.standard_errors_),
            "alpha_offsets": self.alpha_offsets_.tolist(),
            "residual_rms": self.residual_rms_.tolist(),
            "warnings": list(self.warnings_),
            "setup_values": {k: dict(v) for k, v in self.setup_values_.items()},
            "held": dict(self.held_),
            "cost": self.cost_,
            "nfev": self.nfev_,
            "njev": self.njev_,
        }


def _group_weights(episode_of_segment: np.ndarray, groups: Sequence) -> np.ndarray:
    """Per-segment weights under which every group's squared residuals carry the same total weight.

    A group with ``m`` of the ``n`` segments gets the weight ``sqrt(n / (k m))`` (``k`` groups), so
    that its squared residuals, summed, weigh ``n / k`` like every other group's.
    """
    labels = np.array([str(g) for g in groups])[episode_of_segment]
    names, counts = np.unique(labels, return_counts=True)
    per_group = dict(zip(names, np.sqrt(len(labels) / (len(names) * counts))))
    return np.array([per_group[name] for name in labels])


def _marginal_covariance(jtj, q: int, held: Sequence[int] = ()) -> np.ndarray:
    """The top-left q x q block of (J^T J)^-1 from the sparse normal matrix ``jtj`` (the nodes marginalized out).

    ``held``: variables held at a given value; the covariance is conditional on them (their rows and
    columns of ``jtj`` replaced by the identity's, and zero in the result).
    """
    from scipy.sparse import diags

    n = jtj.shape[0]
    if len(held):
        free = np.ones(n)
        free[list(held)] = 0.0
        keep = diags(free, format="csc")
        jtj = keep @ jtj @ keep + diags(1.0 - free, format="csc")
    jtj = jtj + 1e-12 * jtj.diagonal().max() * _identity(n)
    lu = splu(jtj.tocsc())
    rhs = np.zeros((n, q))
    rhs[np.arange(q), np.arange(q)] = 1.0
    cov = lu.solve(rhs)[:q]
    held_rows = [i for i in held if i < q]
    cov[held_rows, :] = 0.0
    cov[:, held_rows] = 0.0
    return cov


def _identity(n: int):
    from scipy.sparse import identity

    return identity(n, format="csc")
