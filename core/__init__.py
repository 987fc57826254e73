"""What every package of the toolkit needs and no single one owns (the lowest shared layer).

Nothing here imports another ``qube_koopman`` package.
"""

from qube_koopman.core.cli import OneLineParser, add_force_option
from qube_koopman.core.files import atomic_path, output_file_problem, output_folder_problem
from qube_koopman.core.signals import Terminated, interrupted_status, sigterm_as_interrupt

__all__ = [
    "OneLineParser",
    "Terminated",
    "add_force_option",
    "atomic_path",
    "interrupted_status",
    "output_file_problem",
    "output_folder_problem",
    "sigterm_as_interrupt",
]
