"""Which model of a fit predicts an episode (:class:`Loop`), and the runs of episodes one batch predicts."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from qube_koopman.core.lti import DiscreteStateSpace, same_system
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.identify.model_selection.sweep import EPISODES_PER_BATCH  # episodes read and simulated together

__all__ = ["Loop", "consecutive_runs"]


@dataclass(frozen=True, eq=False)
class Loop:
    """Which model of a fit predicts an episode.

    Parameters
    ----------
    kind : {"closed", "plant", "wrapped"}
        The fit's closed loop, its plant from the logged input, or its plant wrapped with
        ``controller``.
    controller : DiscreteStateSpace, optional
        The wrapping controller (``"wrapped"``).
    """

    kind: str
    controller: DiscreteStateSpace | None = None

    @classmethod
    def of(cls, controller: DiscreteStateSpace, fitted: DiscreteStateSpace | None, scoring: str = "cl") -> Loop:
        """The loop predicting an episode recorded under ``controller`` by a fit whose closed loop is ``fitted``'s."""
        if scoring == "plant":
            return cls("plant")
        if fitted is not None and same_system(controller, fitted):
            return cls("closed")
        return cls("wrapped", controller)

    def model(self, closed, plant, measured: Sequence[int]):
        """This loop's model of a fit given by its closed loop and plant."""
        if self.kind == "plant":
            return plant
        if self.kind == "closed":
            return closed
        return close_loop(plant, self._wrapping(), measured)

    def same(self, other: Loop) -> bool:
        """Whether the two loops use the same model."""
        return self.kind == other.kind and (self.kind != "wrapped" or same_system(self._wrapping(), other._wrapping()))

    def _wrapping(self) -> DiscreteStateSpace:
        """The controller a ``"wrapped"`` loop wraps the plant with (a ValueError when it has none)."""
        if self.controller is None:
            raise ValueError(f"this {self.kind!r} loop has no controller to wrap the plant with")
        return self.controller


def consecutive_runs(loops: Sequence[Loop], size: int = EPISODES_PER_BATCH) -> list[list[int]]:
    """Indices of consecutive episodes sharing a loop, at most ``size`` at a time (order kept)."""
    runs: list[list[int]] = []
    for i, loop in enumerate(loops):
        if runs and len(runs[-1]) < size and loops[runs[-1][0]].same(loop):
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs
