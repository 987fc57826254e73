"""Multiple shooting for the pendulum: segments, the physical parameterization, residuals.

Each episode is cut into segments of ``horizon`` samples. A segment starts
from its own (free) state, is simulated with the logged voltage held over
each sample (sim's RK4 model, vectorized over all segments at once) and is
compared with the measured angles at each of its ``horizon + 1`` samples; the
measured pendulum angle is the true one plus the episode's encoder zero
offset. Segments share the physical parameters and their episode's offset.

Parameterization (what voltage and angle data can tell apart): the motor
enters only through ``km / Rm`` (torque per volt) and ``km^2 / Rm + Dr``
(arm damping), so ``Rm`` is held at its nominal value and ``km``, ``Dr`` are
fitted (a one-to-one map to those two groups); an amplifier gain would be
confounded with ``km / Rm`` and is not fitted. The whole mass matrix and all
torques can be scaled together without changing the motion, so the masses
``mr``, ``mp`` and the arm length ``Lr`` stay nominal (weighable, measurable)
and set that scale; the pendulum's length-mass group enters through ``Lp``,
which is fitted, and the arm's inertia relative to the pendulum's through
``Jh``, the inertia the arm carries besides its rod (rotor, hub, the
pendulum's encoder at its tip), which is fitted too. So is the transport
delay from command to motor (``delay``, continuous: a fraction of a sample
splits the sample between two commands; segments carry the commands before
them; bounded to 10 ms: the host's latency is part of it, and one session of the
soft controller's logs ran at 4.9 ms against 1.9 ms in the other). Measured on a third
of the paper's training episodes with 0.1 s segments: ``Jh`` lowers the cost by 19 % and the delay (1.0 ms, half a
sample) by 8 % more; ``km`` goes from 0.030 to 0.049 (workbook 0.042) and
``Dr`` comes off its zero bound (``Dp`` stays at zero: the pendulum's own
damping is below what the data resolves, about 1e-6). Without them, ``km`` and ``Lp``
made up for the missing inertia and lag and the closed-loop replay's alpha
and voltage deviations came out 6 to 40 % too large. ``km`` and ``Jh`` are
0.99 correlated (the arm's acceleration per volt is what short segments pin
down best), yet both are identified to better than 1 %. Segments of 0.2 s
(the default) rather than 0.1 s: on simulated logs the 0.1 s fit left the
delay 2.7 standard errors short, and on the rig's logs its replay came out
up to 7 % too quiet (0.2 s: within 5 %). The stiffness ``Kr`` of the cables between the arm's hub
and the base is fitted too (bounded to [0, 0.01] N m/rad; its rest angle stays at the encoder's
zero, where the operator starts an episode): under a soft arm loop the slow load it puts on the
arm is what moved the arm (0.2-0.4 V of restoring voltage at the arm's excursions), and without it
the fit made up for it with ``km`` and ``Jh`` (``km`` 0.050 without the spring, 0.042-0.044 with
one stiffness for all logs, 0.045 with one per recording day; the workbook's 0.042). Two of the
parameters belong to a setup rather than to the rig: the cables' stiffness (dressed anew each
time the rig is set up: the two recording days' logs want 0.19 and 0.59 V/rad at rest) and the delay
(the host's latency: 0.8-1.1 ms in three sessions, 4.3 ms in the soft controller's later one).
Segments may carry, per such parameter, the setup they were recorded in (:attr:`Segments.setups`);
each setup after the first then gets its own value, a variable after the physical ones (the
first keeps the physical variable), and the rest is shared. How the cables' pull levels off as the
arm swings out (``cable_softening``, ``c^2`` in ``Kr tanh(c x) / c``) is shared by the days: fitted on
the 38 logs, 5.2 (levelling beyond 0.44 rad, where the logs' own inverse dynamics level); its square
is what is fitted, because the pull's change with ``c`` itself vanishes at ``c = 0`` (a linear spring).
The Coulomb friction's smoothing speed stays nominal: fitted, it ran to its lower bound without
improving the closed-loop replay (measured).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import lil_matrix

from qube_koopman.sim.pendulum import PendulumParameters, simulate

__all__ = [
    "PHYSICAL",
    "PHYSICAL_NAMES",
    "SETUP_PARAMETERS",
    "n_setup_variables",
    "setup_variables",
    "setup_values",
    "Segments",
    "make_segments",
    "to_params",
    "from_params",
    "residuals",
    "sparsity",
    "jacobian",
    "normal_matrix",
    "simulate_segments",
]

#: Fitted physical parameters: (name, kind, scale, lower, upper). "log": value = nominal exp(z);
#: "linear": value = scale z. Bounds are in the fitted variable z.
PHYSICAL = (
    ("km", "log", 1.0, np.log(0.5), np.log(2.0)),
    ("Dr", "linear", 1e-4, 0.0, 50.0),
    ("Cr", "linear", 1e-4, 0.0, 100.0),
    ("Lp", "log", 1.0, np.log(0.7), np.log(1.4)),
    ("Dp", "linear", 1e-5, 0.0, 100.0),
    ("dead_zone", "linear", 0.1, 0.0, 20.0),
    ("Jh", "linear", 1e-5, 0.0, 100.0),
    ("delay", "linear", 1e-3, 0.0, 10.0),
    ("Kr", "linear", 1e-4, 0.0, 100.0),
    ("cable_softening", "linear", 1.0, 0.0, 100.0),
)
N_PHYSICAL = len(PHYSICAL)
OFFSET_SCALE = 1e-3  # rad per unit of the fitted offset variable
RATE_SCALE = 1.0  # node rates are fitted in rad/s
#: Commands kept before each segment's start: a transport delay up to its bound (10 ms) still applies them.
N_PAST = 6


def to_params(z: np.ndarray, nominal: PendulumParameters) -> PendulumParameters:
    """Physical parameters from the fitted variables."""
    values = {}
    for (name, kind, scale, _, _), zi in zip(PHYSICAL, z):
        values[name] = getattr(nominal, name) * np.exp(zi) if kind == "log" else scale * zi
    return replace(nominal, **{k: float(v) for k, v in values.items()})


def from_params(params: PendulumParameters, nominal: PendulumParameters) -> np.ndarray:
    """The fitted variables of ``params`` (inverse of :func:`to_params`)."""
    z = []
    for name, kind, scale, _, _ in PHYSICAL:
        value = getattr(params, name)
        z.append(np.log(value / getattr(nominal, name)) if kind == "log" else value / scale)
    return np.array(z)


#: The fitted physical parameters' names, in :data:`PHYSICAL`'s order.
PHYSICAL_NAMES = tuple(p[0] for p in PHYSICAL)
#: The parameters a setup may have its own value of (:attr:`Segments.setups`).
SETUP_PARAMETERS = ("Kr", "delay")
#: The parameters each episode may hold at a value of its own, not fitted (:attr:`Segments.fixed`): the base's
#: tilt, which the short segments do not see (it is estimated from the logs' slow balance angle instead).
FIXED_PARAMETERS = ("tilt_x", "tilt_y")


def physical_bounds(seg: "Segments | None" = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the fitted physical variables (and of the segments' setups' ones)."""
    rows = [PHYSICAL[PHYSICAL_NAMES.index(name)] for name, _ in setup_variables(seg)]
    return np.array([p[3] for p in (*PHYSICAL, *rows)]), np.array([p[4] for p in (*PHYSICAL, *rows)])


def setup_variables(seg: "Segments | None") -> list[tuple[str, int]]:
    """The variables the segments' setups add after the physical ones: (parameter, setup) for every setup
    of each parameter after its first (in :data:`SETUP_PARAMETERS`' order)."""
    if seg is None or not seg.setups:
        return []
    return [(n, s) for n in SETUP_PARAMETERS if n in seg.setups for s in range(1, int(seg.setups[n].max()) + 1)]


def n_setup_variables(seg: "Segments") -> int:
    """How many variables the segments' setups add after the physical ones."""
    return len(setup_variables(seg))


def setup_values(phys: np.ndarray, seg: "Segments") -> dict[str, np.ndarray]:
    """Per setup parameter, its value (SI units) in each of its setups, from the physical block
    (``phys``: the physical variables, then the setups')."""
    out = {}
    extra = dict(zip(setup_variables(seg), phys[N_PHYSICAL:]))
    for name in SETUP_PARAMETERS:
        if seg.setups and name in seg.setups:
            i = PHYSICAL_NAMES.index(name)
            z = [phys[i]] + [extra[name, s] for s in range(1, int(seg.setups[name].max()) + 1)]
            out[name] = PHYSICAL[i][2] * np.asarray(z, dtype=float)  # both are "linear" variables
    return out


@dataclass(frozen=True)
class Segments:
    """Shooting segments of several episodes, stacked along the last axis.

    Attributes
    ----------
    y : ndarray (horizon + 1, n_seg, 2)
        Measured angles over each segment.
    u : ndarray (horizon, n_seg)
        Voltage held over each sample.
    episode : ndarray (n_seg,)
        Index of each segment's episode.
    start : ndarray (n_seg,)
        First sample of each segment in its episode.
    past : ndarray (N_PAST, n_seg) or None
        The commands before each segment, oldest first (for a transport delay).
    weight : ndarray (n_seg,) or None
        Each segment's residuals are multiplied by its weight (None: all 1), so
        that groups of episodes can count alike whatever their number.
    setups : dict of str to ndarray of int (n_seg,), optional
        Per parameter of :data:`SETUP_PARAMETERS`, each segment's setup (0, 1, ...), whose value of
        that parameter it simulates with; a parameter left out is shared.
    fixed : dict of str to ndarray (n_seg,), optional
        Per parameter the fit does not fit (:data:`FIXED_PARAMETERS`: the base's tilt), each
        segment's value of it, held as given (its episode's; for example its day's tilt).
    load : ndarray (horizon, n_seg) or None
        A known torque on the arm over each sample, in volts at the motor past the dead zone (for
        example the cables' relaxation from the logged arm angle); None: none.
    """

    y: np.ndarray
    u: np.ndarray
    episode: np.ndarray
    start: np.ndarray
    past: np.ndarray | None = None
    weight: np.ndarray | None = None
    setups: dict | None = None
    fixed: dict | None = None
    load: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.u.shape[1]

    @property
    def horizon(self) -> int:
        return self.u.shape[0]


def make_segments(
    measured: list[np.ndarray],
    voltages: list[np.ndarray],
    horizon: int,
    skip: int,
    delay: int = 0,
    stride: int | None = None,
    loads: list[np.ndarray] | None = None,
) -> Segments:
    """Cut episodes into segments of ``horizon`` samples, every ``stride`` samples from ``skip``.

    ``delay`` whole samples of transport delay: the voltage logged at sample
    ``k - delay`` acts over sample ``k``. ``loads``: per episode, a known torque on the arm at each
    sample (:attr:`Segments.load`; not delayed).
    """
    stride = horizon if stride is None else stride
    ys, us, pasts, eps, starts, ds = [], [], [], [], [], []
    for e, (y, u) in enumerate(zip(measured, voltages)):
        u = np.concatenate([np.zeros(delay), u[: len(u) - delay]]) if delay else u
        padded = np.concatenate([np.zeros(N_PAST), u])  # zero volts before the log's start
        for k in range(max(skip, delay), len(y) - horizon, stride):
            ys.append(y[k : k + horizon + 1])
            us.append(u[k : k + horizon])
            pasts.append(padded[k : k + N_PAST])
            eps.append(e)
            starts.append(k)
            if loads is not None:
                ds.append(loads[e][k : k + horizon])
    if not ys:
        raise ValueError(f"no segment of {horizon} samples fits after skipping {skip}")
    return Segments(
        np.stack(ys, axis=1),
        np.stack(us, axis=1),
        np.array(eps),
        np.array(starts),
        np.stack(pasts, axis=1),
        load=np.stack(ds, axis=1) if loads is not None else None,
    )


def simulate_segments(
    nodes: np.ndarray,
    u: np.ndarray,
    params: PendulumParameters | list[PendulumParameters],
    dt: float,
    n_substeps: int = 2,
    past: np.ndarray | None = None,
    load: np.ndarray | None = None,
) -> np.ndarray:
    """Angles (horizon + 1, n_seg, 2) from node states (n_seg, 4) under voltages (horizon, n_seg).

    ``past`` (n_past, n_seg): the commands before each segment, which a transport delay still applies.
    ``params``: the pendulum, or one per segment. ``load`` (horizon, n_seg): :attr:`Segments.load`.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return simulate(nodes, u, params, dt, n_substeps, past_voltages=past, loads=load)[..., :2]


def unpack(z: np.ndarray, n_episodes: int, n_seg: int, n_extra: int = 0):
    """(physical variables, offsets in rad, node states (n_seg, 4)) from the full variable vector.

    The physical variables include the ``n_extra`` setups' ones after :data:`PHYSICAL`'s.
    """
    n_phys = N_PHYSICAL + n_extra
    phys = z[:n_phys]
    offsets = OFFSET_SCALE * z[n_phys : n_phys + n_episodes]
    nodes = z[n_phys + n_episodes :].reshape(n_seg, 4).copy()
    nodes[:, 2:] *= RATE_SCALE
    return phys, offsets, nodes


def residuals(
    z: np.ndarray, seg: Segments, n_episodes: int, nominal: PendulumParameters, dt: float, sigma: float
) -> np.ndarray:
    """Scaled prediction errors, ordered (segment, sample, angle)."""
    n_extra = n_setup_variables(seg)
    phys, offsets, nodes = unpack(z, n_episodes, seg.n, n_extra)
    # With setups every segment simulates with its setups' values, all in one batch.
    pred = simulate_segments(nodes, seg.u, _segment_twins(phys, seg, nominal), dt, past=seg.past, load=seg.load)
    pred[..., 1] += offsets[seg.episode]
    r = (pred - seg.y) / sigma
    if seg.weight is not None:
        r = r * seg.weight[None, :, None]
    r = np.nan_to_num(r, nan=1e6, posinf=1e6, neginf=-1e6)
    return r.transpose(1, 0, 2).ravel()


def sparsity(seg: Segments, n_episodes: int):
    """Jacobian pattern: physical variables touch every residual, an offset its episode's alpha
    residuals, a node its segment's residuals."""
    per_seg = 2 * (seg.horizon + 1)
    n_res = seg.n * per_seg
    n_phys = N_PHYSICAL + n_setup_variables(seg)
    n_var = n_phys + n_episodes + 4 * seg.n
    pattern = lil_matrix((n_res, n_var), dtype=np.int8)
    pattern[:, :n_phys] = 1
    rows = np.arange(n_res)
    segment_of_row = rows // per_seg
    alpha_rows = rows[rows % 2 == 1]
    pattern[alpha_rows, n_phys + seg.episode[segment_of_row[alpha_rows]]] = 1
    for j in range(4):
        pattern[rows, n_phys + n_episodes + 4 * segment_of_row + j] = 1
    return pattern.tocsr()


def jacobian(
    z: np.ndarray,
    r0: np.ndarray,
    seg: Segments,
    n_episodes: int,
    nominal: PendulumParameters,
    dt: float,
    sigma: float,
    physics: bool = True,
    method: str = "tangents",
):
    """Sparse Jacobian of :func:`residuals` in the :func:`sparsity` pattern.

    ``method="tangents"`` (the default): the simulation's forward sensitivities
    (:func:`~qube_koopman.sim.pendulum.sensitivity.simulate_tangents`), every node and physical
    variable along one simulation; ``"differences"``: forward differences, one residual evaluation
    per physical variable and four for all the nodes at once (a node touches only its own segment).
    The offsets enter linearly and need neither. ``physics=False``: the physical variables are held
    fixed and their columns left empty.
    """
    n_all = N_PHYSICAL + n_setup_variables(seg)  # the physical block, with the setups' variables
    if method == "tangents":
        data = _tangent_rows(z, seg, n_episodes, nominal, dt, sigma, physics)
    elif method == "differences":
        phys_data, node_data = _difference_columns(z, r0, seg, n_episodes, nominal, dt, sigma, physics)
        data = _pair_rows(seg, phys_data, node_data, sigma)
    else:
        raise ValueError(f"unknown Jacobian method {method!r}; expected 'tangents' or 'differences'")
    return _assemble(seg, n_episodes, n_all, data)


def _difference_columns(z, r0, seg: Segments, n_episodes: int, nominal, dt: float, sigma: float, physics: bool):
    """The physical variables' and the nodes' columns of the Jacobian by forward differences."""
    n_res = seg.n * 2 * (seg.horizon + 1)
    n_all = N_PHYSICAL + n_setup_variables(seg)
    base = n_all + n_episodes
    n_phys = n_all if physics else 0
    phys_data = np.empty((n_res, n_phys))
    for i in range(n_phys):
        step = 1e-6 * max(1.0, abs(z[i]))
        zi = z.copy()
        zi[i] += step
        phys_data[:, i] = (residuals(zi, seg, n_episodes, nominal, dt, sigma) - r0) / step
    node_data = np.empty((n_res, 4))
    for j in range(4):
        zj = z.copy()
        zj[base + j :: 4] += 1e-6
        node_data[:, j] = (residuals(zj, seg, n_episodes, nominal, dt, sigma) - r0) / 1e-6
    return phys_data, node_data


def _coefficient_row(p: PendulumParameters) -> np.ndarray:
    """A pendulum's coefficients in :data:`~qube_koopman.sim.pendulum.sensitivity.FIELDS`' order."""
    from qube_koopman.sim.pendulum.physics import Coefficients
    from qube_koopman.sim.pendulum.sensitivity import FIELDS

    k = Coefficients.of(p)._asdict()
    k["cable_softening"] = p.cable_softening
    return np.array([k[name] for name in FIELDS], dtype=float)


def _segment_twins(phys: np.ndarray, seg: Segments, nominal: PendulumParameters):
    """The pendulum each segment simulates with (one, or a list of one per segment, as :func:`residuals`)."""
    params = to_params(phys, nominal)
    if not seg.setups and not seg.fixed:
        return params
    setups, fixed_values = seg.setups or {}, seg.fixed or {}
    values = setup_values(phys, seg) if setups else {}
    names, fixed = list(values), list(fixed_values)
    columns = [setups[name].astype(float) for name in names] + [fixed_values[name] for name in fixed]
    combinations, index = np.unique(np.column_stack(columns), axis=0, return_inverse=True)
    twins = [
        replace(
            params,
            **{n: float(values[n][int(c)]) for n, c in zip(names, row)},
            **{n: float(v) for n, v in zip(fixed, row[len(names) :])},
        )
        for row in combinations
    ]
    return [twins[i] for i in index.ravel()]


def _tangent_rows(z, seg: Segments, n_episodes: int, nominal, dt: float, sigma: float, physics: bool):
    """The Jacobian's entries in :func:`_assemble`'s layout (:func:`_pair_rows`) from the simulation's tangents.

    A variable's direction is the derivative of the coefficients and the delay of the segments it
    moves (central differences of the cheap map from the variables to the coefficients); a setup's
    own variable, and the physical one of a parameter that setups share out, move only their
    setup's segments.
    """
    from qube_koopman.sim.pendulum.sensitivity import FIELDS, Directions, simulate_tangents

    n_extra = n_setup_variables(seg)
    n_all = N_PHYSICAL + n_extra
    phys, _, nodes = unpack(z, n_episodes, seg.n, n_extra)
    twins = _segment_twins(phys, seg, nominal)
    n_phys = n_all if physics else 0
    n_dir = 4 + n_phys
    state = np.zeros((n_dir, 4))
    state[np.arange(4), np.arange(4)] = [1.0, 1.0, RATE_SCALE, RATE_SCALE]
    coefficients = np.zeros((n_dir, len(FIELDS)))
    delay = np.zeros(n_dir)
    mask = np.ones((n_dir, seg.n)) if seg.setups else None
    extra = setup_variables(seg)
    lower = physical_bounds(seg)[0]
    for i in range(n_phys):
        # The setup this variable is the value of (None: every segment's), and a segment showing it.
        name, setup = (PHYSICAL_NAMES[i], 0) if i < N_PHYSICAL else extra[i - N_PHYSICAL]
        owner = seg.setups.get(name) if seg.setups else None
        shows = np.flatnonzero(owner == setup) if owner is not None else np.array([0])
        if shows.size == 0:
            continue
        step = 1e-6 * max(1.0, abs(z[i]))
        up, down = phys.copy(), phys.copy()
        up[i] += step
        down[i] = max(down[i] - step, lower[i])  # central, but forward at the lower bound (Cr = 0 is one)
        p_up, p_down = (_segment_twins(v, seg, nominal) for v in (up, down))
        if isinstance(p_up, list):
            p_up, p_down = p_up[shows[0]], p_down[shows[0]]
        coefficients[4 + i] = (_coefficient_row(p_up) - _coefficient_row(p_down)) / (up[i] - down[i])
        delay[4 + i] = (p_up.delay - p_down.delay) / (up[i] - down[i])
        if owner is not None and mask is not None:
            mask[4 + i] = owner == setup
    with np.errstate(over="ignore", invalid="ignore"):
        _, tangents = simulate_tangents(
            nodes,
            seg.u,
            twins,
            Directions(state, coefficients, delay, mask),
            dt,
            past_voltages=seg.past,
            loads=seg.load,
        )
    # (sample, direction, segment, angle) to the residuals' pairs of rows (segment, sample), each
    # theta's then alpha's entries (_pair_rows), written in place: the tangents are the fit's largest
    # array (50 MB on the 38 calibration logs), and its copies, reshaped, divided, weighted and
    # interleaved one after the other, took a third of a Jacobian's time (measured). The same
    # operations on the same numbers: the same entries, bit for bit.
    n_phys = n_dir - 4
    along = tangents.transpose(2, 0, 3, 1)  # (segment, sample, angle, direction): a view
    data = np.empty((seg.n, seg.horizon + 1, 2 * n_phys + 9))
    theta, alpha = data[..., : n_phys + 4], data[..., n_phys + 4 :]
    np.divide(along[:, :, 0, 4:], sigma, out=theta[..., :n_phys])
    np.divide(along[:, :, 0, :4], sigma, out=theta[..., n_phys:])
    np.divide(along[:, :, 1, 4:], sigma, out=alpha[..., :n_phys])
    np.divide(along[:, :, 1, :4], sigma, out=alpha[..., n_phys + 1 :])
    alpha[..., n_phys] = 0.0  # the offset's entry, written below
    if seg.weight is not None:
        data *= seg.weight[:, None, None]
    np.copyto(data, 0.0, where=~np.isfinite(data))  # a diverged segment's residuals are clamped: flat
    alpha[..., n_phys] = _offset_entries(seg, sigma).reshape(seg.n, seg.horizon + 1)
    return data.reshape(-1, data.shape[-1])


def _offset_entries(seg: Segments, sigma: float) -> np.ndarray:
    """Each pair of rows' entry in its episode's offset (alpha only; exact: the offset enters linearly)."""
    segment_of_pair = np.arange(seg.n * (seg.horizon + 1)) // (seg.horizon + 1)
    weight = 1.0 if seg.weight is None else seg.weight[segment_of_pair]
    return np.full(segment_of_pair.size, OFFSET_SCALE / sigma) * weight


def _pair_rows(seg: Segments, phys_data: np.ndarray, node_data: np.ndarray, sigma: float) -> np.ndarray:
    """The Jacobian's entries by pairs of rows (a sample's theta, then its alpha), as :func:`_assemble` lays
    them out: theta's physical and node columns, then alpha's physical columns, the episode's offset and
    the nodes, from the physical and node columns (one row per residual)."""
    offset_data = _offset_entries(seg, sigma)
    return np.concatenate(
        [phys_data[0::2], node_data[0::2], phys_data[1::2], offset_data[:, None], node_data[1::2]], axis=1
    )


def _assemble(seg: Segments, n_episodes: int, n_all: int, data: np.ndarray):
    """The Jacobian in CSR from its entries by pairs of rows (:func:`_pair_rows`)."""
    from scipy.sparse import csr_matrix

    n_res = seg.n * 2 * (seg.horizon + 1)
    n_phys = (data.shape[1] - 9) // 2
    base = n_all + n_episodes
    # Built in CSR directly: each pair of rows (a sample's theta, then its alpha) holds the physical
    # columns, the episode's offset (alpha only) and the segment's four nodes, in the ascending column
    # order scipy's conversion from (row, column) triplets gave (the same matrix, bit for bit); that
    # conversion took 5 of the 58 s of a fit on the dataset's 38 calibration logs (profiled).
    # The indices in the integer type scipy keeps them in (32 bits while they fit): given 64-bit ones,
    # it scans them and copies them over at every Jacobian.
    n_var = base + 4 * seg.n
    index: np.dtype = np.dtype(np.int32 if max(n_var, data.size) < np.iinfo(np.int32).max else np.int64)
    segment_of_pair = np.arange(n_res // 2, dtype=index) // (seg.horizon + 1)
    phys_cols = np.broadcast_to(np.arange(n_phys, dtype=index), (segment_of_pair.size, n_phys))
    node_cols = base + 4 * segment_of_pair[:, None] + np.arange(4, dtype=index)
    offset_cols = (n_all + seg.episode[segment_of_pair].astype(index))[:, None]
    cols = np.concatenate([phys_cols, node_cols, phys_cols, offset_cols, node_cols], axis=1)
    pairs = np.tile(np.array([n_phys + 4, n_phys + 5], dtype=index), segment_of_pair.size)
    indptr = np.concatenate([np.zeros(1, dtype=index), np.cumsum(pairs, dtype=index)])
    return csr_matrix((data.ravel(), cols.ravel(), indptr), shape=(n_res, n_var))


def normal_matrix(jac, seg: Segments, n_episodes: int):
    """``J^T J`` (CSC) of a :func:`jacobian`, from its arrow shape.

    Every entry of ``J^T J`` is a sum over the rows of one segment (the node blocks, their coupling
    to the physics and to the episode's offset) or of the segments summed (the physics' block, an
    offset's), and a segment's pairs of rows (theta, then alpha) hold the same columns: one batched
    product of each segment's pairs with themselves gives them all. scipy's general sparse product
    of the same matrix took 0.26 s of a 38-log fit's 2.5 s iteration (measured). ``jac`` must be
    laid out as :func:`jacobian` lays it out.
    """
    from scipy.sparse import coo_matrix

    n_all = N_PHYSICAL + n_setup_variables(seg)
    width = jac.indptr[2] - jac.indptr[0]  # a pair's entries: theta's n_phys + 4, alpha's n_phys + 5
    n_phys = (width - 9) // 2
    pairs = jac.data.reshape(seg.n, seg.horizon + 1, width)
    products = np.matmul(pairs.transpose(0, 2, 1), pairs)  # (segment, width, width)
    theta_phys, theta_nodes = np.arange(n_phys), n_phys + np.arange(4)
    alpha_phys, offset, alpha_nodes = n_phys + 4 + np.arange(n_phys), 2 * n_phys + 4, 2 * n_phys + 5 + np.arange(4)

    def block(a_theta, b_theta, a_alpha, b_alpha):  # the theta rows' and the alpha rows' sums, per segment
        return products[:, a_theta[:, None], b_theta] + products[:, a_alpha[:, None], b_alpha]

    pp = block(theta_phys, theta_phys, alpha_phys, alpha_phys).sum(axis=0)
    pn = block(theta_phys, theta_nodes, alpha_phys, alpha_nodes)  # (segment, n_phys, 4)
    nn = block(theta_nodes, theta_nodes, alpha_nodes, alpha_nodes)  # (segment, 4, 4)
    po, on, oo = products[:, alpha_phys, offset], products[:, offset, alpha_nodes], products[:, offset, offset]
    po_episode, oo_episode = np.zeros((n_episodes, n_phys)), np.zeros(n_episodes)
    np.add.at(po_episode, seg.episode, po)
    np.add.at(oo_episode, seg.episode, oo)
    nodes = n_all + n_episodes + 4 * np.arange(seg.n)[:, None] + np.arange(4)  # (segment, 4)
    offsets = n_all + np.arange(n_episodes)
    phys = np.arange(n_phys)
    # The blocks off the diagonal, each entered on both sides; then the diagonal blocks.
    off_diagonal = [
        (np.broadcast_to(phys[None, :, None], pn.shape), np.broadcast_to(nodes[:, None, :], pn.shape), pn),
        (np.broadcast_to(phys, po_episode.shape), np.broadcast_to(offsets[:, None], po_episode.shape), po_episode),
        (np.broadcast_to((n_all + seg.episode)[:, None], on.shape), nodes, on),
    ]
    diagonal = [
        (np.repeat(phys, n_phys), np.tile(phys, n_phys), pp),
        (offsets, offsets, oo_episode),
        (np.broadcast_to(nodes[:, :, None], nn.shape), np.broadcast_to(nodes[:, None, :], nn.shape), nn),
    ]
    rows = [r.ravel() for r, _, _ in off_diagonal] + [c.ravel() for _, c, _ in off_diagonal]
    cols = [c.ravel() for _, c, _ in off_diagonal] + [r.ravel() for r, _, _ in off_diagonal]
    values = [v.ravel() for _, _, v in off_diagonal] * 2
    rows += [r.ravel() for r, _, _ in diagonal]
    cols += [c.ravel() for _, c, _ in diagonal]
    values += [v.ravel() for _, _, v in diagonal]
    n_var = n_all + n_episodes + 4 * seg.n
    normal = coo_matrix(
        (np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(n_var, n_var)
    ).tocsc()
    normal.eliminate_zeros()  # a setup's variable is zero on the other setups' segments: as the general product
    return normal
