"""What every package of the toolkit needs and no single one owns (the lowest shared layer).

Nothing here imports another ``qube_koopman`` package.
"""

from qube_koopman.core.files import atomic_path

__all__ = ["atomic_path"]
