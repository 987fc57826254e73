"""How many workers (processes or threads) a command runs: joblib's convention, -1 for every core."""

from __future__ import annotations

__all__ = ["resolve_n_jobs"]


def resolve_n_jobs(n_jobs: int, n_episodes: int, name: str = "n_jobs") -> int:
    """Workers (processes or threads) for ``n_episodes`` episodes, joblib's convention: -1 for every core.

    Parameters
    ----------
    n_jobs : int
        -1 (every core this process may run on: ``joblib.cpu_count()``, which honours the
        affinity mask and cgroup quotas) or a positive count.
    n_episodes : int
        Episodes to run: never more workers than these, and at least one.
    name : str
        The caller's name for ``n_jobs``, in the error.

    Returns
    -------
    int

    Raises
    ------
    ValueError
        For 0 or a value below -1.
    """
    if n_jobs == 0 or n_jobs < -1:
        raise ValueError(f"{name} must be -1 (every core) or at least 1, got {n_jobs}")
    if n_jobs == -1:
        import joblib

        n_jobs = joblib.cpu_count()
    return max(1, min(n_jobs, n_episodes))
