"""What every package of the toolkit needs and no single one owns (the lowest shared layer).

Nothing here imports another ``qube_koopman`` package. The names below are imported when first
used (:func:`~qube_koopman.core.exports.lazy_exports`): every package imports ``core``, and its
import costs the ``__init__`` alone, not argparse, hashing or signal handling.
"""

from qube_koopman.core.exports import lazy_exports

#: Each public name and the module of ``core`` that defines it.
_HOMES = {
    "ControllerInfo": "controller_file",
    "load_controller": "controller_file",
    "write_controller_file": "controller_file",
    "register_controller_kind": "controller_file",
    "registered_controller_kinds": "controller_file",
    "PdGains": "controller",
    "pd_controller": "controller",
    "pi_controller": "controller",
    "load_pd_gains": "controller",
    "DiscreteStateSpace": "lti",
    "replay_controller": "lti",
    "spectral_radius": "lti",
    "same_system": "lti",
    "OneLineParser": "cli",
    "add_force_option": "cli",
    "atomic_path": "files",
    "remove_stale_parts": "files",
    "limited_blas_threads": "blas",
    "output_file_problem": "files",
    "output_folder_problem": "files",
    "Terminated": "signals",
    "interrupted_status": "signals",
    "sigterm_as_interrupt": "signals",
}

__all__ = sorted(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
