"""Controllers built from gains: discrete LTI systems for the loop, the logs and identification.

Every controller maps the tracking error ``e = r - y`` (one channel per fed-back
state) to one plant input, as the sum of one SISO block per channel. Blocks
are discretized as python-control's ``sample_system`` does (``_sample_block``)
and each first-order block is scaled to ``B = 1``, the realization the rig
and the reference code used, so logged controller states match theirs. The rig's
PD derivative filter was discretized by backward Euler, not the zero-order hold the paper's
text names: backward Euler reproduces the dataset's logged control output to 1e-14 V, ZOH is
off by up to 1.7 V. The Duffing example's PI controller is ZOH-discretized.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from qube_koopman.core.files import loads_toml, read_bounded_text
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "DISCRETIZATIONS",
    "MAX_CONTROLLER_BYTES",
    "PdGains",
    "SHIPPED_CONTROLLERS",
    "controller_file",
    "load_pd_gains",
    "pd_gains_from_table",
    "read_controller_toml",
    "pd_controller",
    "pi_controller",
    "discretize_channels",
]

# Our names -> scipy.signal.cont2discrete's (which control.sample_system uses, and _sample_block follows).
DISCRETIZATIONS = {"backward-euler": "backward_diff", "zoh": "zoh", "tustin": "bilinear"}

QUBE_SAMPLE_PERIOD = 1.0 / 500.0
#: The largest controller file read (a 2000-state controller written inline is about 100 MB).
MAX_CONTROLLER_BYTES = 256 * 2**20


@dataclass(frozen=True)
class PdGains:
    """Gains of the QUBE-Servo's two filtered PD channels (V/rad, V s/rad, rad/s).

    Each channel is ``K = -kp - kd tau s / (s + tau)`` on the tracking error.

    Parameters
    ----------
    kp_theta, kd_theta : float
        The arm channel's proportional (V/rad) and derivative (V s/rad) gains.
    kp_alpha, kd_alpha : float
        The pendulum channel's.
    tau : float
        The derivative filter's bandwidth (rad/s).
    """

    kp_theta: float
    kd_theta: float
    kp_alpha: float
    kd_alpha: float
    tau: float

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not np.isfinite(value):
                raise ValueError(f"gain {name} must be a finite number, got {value!r}")
        if self.tau <= 0:
            raise ValueError(f"derivative filter tau must be positive, got {self.tau}")

    def as_dict(self) -> dict:
        """Plain-data form, as in controller.toml."""
        return {k: float(v) for k, v in asdict(self).items()}


#: Controller files shipped with the package, by the name ``--controller`` accepts.
SHIPPED_CONTROLLERS = {
    "rig": "rig_controller.toml",  # the gains that recorded the paper's dataset
    "soft-theta": "soft_theta_controller.toml",  # a softer arm: the README's transfer example
}


def controller_file(name_or_path: str | Path) -> Path:
    """The path of a controller file: an existing file, or a shipped one by name.

    A name of :data:`SHIPPED_CONTROLLERS` (``"rig"``, ``"soft-theta"``) that is
    not also a file in the working folder gives the package's file (a folder of
    that name, such as episodes in ``./rig``, does not count); anything else is
    taken as a path (and reported by :func:`read_controller_toml` if missing).
    """
    path = Path(name_or_path)
    if str(name_or_path) in SHIPPED_CONTROLLERS and not path.is_file():
        # resources.files on the package's own name: the file is found in a wheel as in a checkout.
        return Path(str(resources.files(__package__) / SHIPPED_CONTROLLERS[str(name_or_path)]))
    return path


def read_controller_toml(path: Path) -> dict:
    """The TOML table of a controller file (either kind).

    Raises
    ------
    ValueError
        Naming the file when it cannot be read or is not TOML.
    """
    # A FIFO, a device, a file over MAX_CONTROLLER_BYTES or nested too deep: a ValueError naming the file.
    try:
        return loads_toml(read_bounded_text(path, MAX_CONTROLLER_BYTES, "controller file"), path)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read controller file ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (a TOML controller file is expected)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from None


def pd_gains_from_table(data: dict, path: Path) -> PdGains:
    """The gains of a PD gains file's table (:func:`read_controller_toml`); errors name ``path``."""
    fields = PdGains.__dataclass_fields__
    missing = [k for k in fields if k not in data]
    if missing:
        raise ValueError(f"{path}: missing gains {', '.join(missing)}")
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{path}: unknown keys {', '.join(unknown)}")
    try:
        return PdGains(**{k: data[k] for k in fields})
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def load_pd_gains(path: str | Path) -> PdGains:
    """Read the gains from a controller.toml like the dataset's, or a shipped one by name.

    Parameters
    ----------
    path : str or Path
        A controller file, or a name of :data:`SHIPPED_CONTROLLERS` (:func:`controller_file`).

    Raises
    ------
    ValueError
        Naming the file when it cannot be read, is not TOML or misses a gain.
    """
    path = controller_file(path)
    return pd_gains_from_table(read_controller_toml(path), path)


def discretize_channels(channels, dt: float, method: str) -> DiscreteStateSpace:
    """Discretize continuous SISO blocks and sum them into one multi-input controller.

    Parameters
    ----------
    channels : sequence of control.TransferFunction
        One continuous SISO block per error channel.
    dt : float
        Sample period in seconds.
    method : {"backward-euler", "zoh", "tustin"}
        Discretization of each block.
    """
    import control  # lazily: python-control imports matplotlib

    blocks = []
    for channel in channels:
        sys = control.ss(channel)
        blocks.append(tuple(np.atleast_2d(np.asarray(m, dtype=float)) for m in (sys.A, sys.B, sys.C, sys.D)))
    return _discrete_sum(blocks, dt, method)


def _check_method(method: str) -> None:
    if method not in DISCRETIZATIONS:
        raise ValueError(f"unknown discretization {method!r}; expected one of {', '.join(DISCRETIZATIONS)}")


def _sample_block(A, B, C, D, dt: float, method: str) -> tuple[np.ndarray, ...]:
    """One continuous block ``(A, B, C, D)`` discretized as ``scipy.signal.cont2discrete`` does.

    The same formulas as SciPy's (and so python-control's ``sample_system``): the zero-order
    hold from the matrix exponential of ``[[A, B], [0, 0]] dt``, backward Euler and Tustin as
    the generalized bilinear transform with alpha 1 and 1/2. Written here because importing
    python-control (which imports scipy.signal and matplotlib) takes longer than a one-episode
    ``qube-run`` simulates, and every command that builds a PD controller paid it;
    tests/core/test_controller_discretization.py holds it to python-control's result.

    Parameters
    ----------
    A, B, C, D : array_like
        The continuous block (2-D).
    dt : float
        Sample period in seconds.
    method : {"backward-euler", "zoh", "tustin"}
        The discretization.

    Returns
    -------
    tuple of ndarray
        The discrete ``(A, B, C, D)``.
    """
    from scipy import linalg

    _check_method(method)
    A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (A, B, C, D))
    n, m = B.shape
    if method == "zoh":
        exponential = linalg.expm(dt * np.block([[A, B], [np.zeros((m, n)), np.zeros((m, m))]]))[:n]
        return exponential[:, :n], exponential[:, n:], C, D
    weight = 1.0 if method == "backward-euler" else 0.5  # scipy's gbt alpha
    ima = np.eye(n) - weight * dt * A
    Ad = linalg.solve(ima, np.eye(n) + (1.0 - weight) * dt * A)
    Bd = linalg.solve(ima, dt * B)
    Cd = linalg.solve(ima.T, C.T).T
    return Ad, Bd, Cd, D + weight * (C @ Bd)


def _first_order(pole: float, residue: float, feedthrough: float) -> tuple:
    """The block ``feedthrough + residue / (s - pole)``: one state, or none when ``residue`` is 0 (a
    static gain, as python-control's transfer-function arithmetic leaves it)."""
    if residue == 0:
        return _static([[feedthrough]])
    return [[pole]], [[1.0]], [[residue]], [[feedthrough]]


def _static(D) -> tuple:
    """A block without states: the gain ``D`` (1 x 1)."""
    return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.atleast_2d(np.asarray(D, dtype=float))


def _discrete_sum(blocks, dt: float, method: str) -> DiscreteStateSpace:
    """Continuous SISO blocks ``(A, B, C, D)``, each discretized (first-order ones scaled to
    ``B = 1``, the rig's realization) and summed into one controller with an input per block."""
    _check_method(method)
    discrete = []
    for block in blocks:
        A, B, C, D = _sample_block(block[0], block[1], block[2], block[3], dt, method) if np.size(block[0]) else block
        if A.shape == (1, 1) and B[0, 0] != 0:
            # Scale the state so that B = 1 (same transfer function, the rig's realization).
            C, B = C * B[0, 0], np.ones((1, 1))
        discrete.append((A, B, C, D))
    n = sum(b[0].shape[0] for b in discrete)
    A = np.zeros((n, n))
    B = np.zeros((n, len(discrete)))
    C = np.zeros((1, n))
    D = np.zeros((1, len(discrete)))
    i = 0
    for j, (Ab, Bb, Cb, Db) in enumerate(discrete):
        k = Ab.shape[0]
        A[i : i + k, i : i + k] = Ab
        B[i : i + k, j] = Bb[:, 0]
        C[0, i : i + k] = Cb[0]
        D[0, j] = Db[0, 0]
        i += k
    return DiscreteStateSpace(A, B, C, D, dt)


def pd_controller(gains: PdGains, dt: float = QUBE_SAMPLE_PERIOD, method: str = "backward-euler") -> DiscreteStateSpace:
    """The QUBE-Servo's two filtered PD channels (theta, alpha) as one discrete controller.

    ``method="backward-euler"`` is what ran on the rig (it reproduces the
    dataset's control_output to 1e-14 V); the paper's text says ZOH.

    Parameters
    ----------
    gains : PdGains
        The two channels' gains.
    dt : float
        Sample period (s).
    method : str
        The discretization: ``"backward-euler"``, ``"zoh"`` or ``"tustin"``.

    Returns
    -------
    DiscreteStateSpace
        Inputs the tracking errors of theta and alpha, output the voltage.
    """
    # -(kp + kd tau s / (s + tau)) = -(kp + kd tau) + kd tau^2 / (s + tau): one state per channel
    tau = gains.tau
    blocks = [
        _first_order(-tau, kd * tau**2, -(kp + kd * tau))
        for kp, kd in ((gains.kp_theta, gains.kd_theta), (gains.kp_alpha, gains.kd_alpha))
    ]
    return _discrete_sum(blocks, dt, method)


def pi_controller(kp: float, ki: float, dt: float, method: str = "zoh") -> DiscreteStateSpace:
    """A SISO PI controller ``kp + ki / s`` (the Duffing example's, with kp = ki = 1).

    Parameters
    ----------
    kp, ki : float
        Proportional and integral gains.
    dt : float
        Sample period (s).
    method : str
        The discretization: ``"zoh"``, ``"backward-euler"`` or ``"tustin"``.

    Returns
    -------
    DiscreteStateSpace
    """
    return _discrete_sum([_first_order(0.0, ki, kp)], dt, method)  # kp + ki / s
