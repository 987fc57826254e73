"""The cluster runner's wait for a result, against a future that finishes as the wait gives up."""

from __future__ import annotations

import pytest
from qube_koopman.identify.model_selection.distributed import ordered_results


class _LateFuture:
    """Finishes just after the first timed wait on it ran out (as on a loaded machine)."""

    def __init__(self, value=None, error: BaseException | None = None) -> None:
        self.value, self.error, self.waits = value, error, 0

    def result(self, timeout=None):
        self.waits += 1
        if self.waits == 1:
            raise TimeoutError(f"timed out after {timeout} s.")
        if self.error is not None:
            raise self.error
        return self.value

    def done(self) -> bool:
        return self.waits >= 1


class _Client:
    def __init__(self, futures) -> None:
        self.futures = list(futures)

    def nthreads(self) -> dict:
        return {"tcp://worker": 1}

    def submit(self, fn, *args, pure=False, **kwargs):
        return self.futures.pop(0)


def test_a_result_that_comes_as_the_wait_runs_out_is_the_result():
    client = _Client([_LateFuture(1), _LateFuture(2)])
    assert list(ordered_results(client, [(abs, (1,), {}), (abs, (2,), {})], worker_timeout=5.0)) == [1, 2]


def test_a_call_that_fails_as_the_wait_runs_out_raises_its_own_error():
    client = _Client([_LateFuture(error=TimeoutError("the call's own"))])
    with pytest.raises(TimeoutError, match="the call's own"):
        list(ordered_results(client, [(abs, (1,), {})], worker_timeout=5.0))
