"""What every package of the toolkit needs and no single one owns (the lowest shared layer).

Nothing here imports another ``qube_koopman`` package.
"""

from qube_koopman.core.cli import OneLineParser
from qube_koopman.core.files import atomic_path
from qube_koopman.core.signals import Terminated, interrupted_status, run_interruptible, sigterm_as_interrupt

__all__ = ["OneLineParser", "atomic_path", "Terminated", "interrupted_status", "run_interruptible", "sigterm_as_interrupt"]
