"""Per-episode sensor offsets: analytic recovery, offset-aware prediction, refusals."""

from dataclasses import replace

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, r2_score
from qube_koopman.identify.models.offsets import OffsetWarning, estimate_offsets, predict_estimating_offsets
from linear_loops import closed_loop_trajectories, mass_spring_damper, pid_position_controller

OFFSET = 0.03


@pytest.fixture(scope="module")
def fitted():
    A_p, B_p = mass_spring_damper()
    controller = pid_position_controller()
    trajs = closed_loop_trajectories(A_p, B_p, controller, [0], n_episodes=4, seed=3)
    model = ClEdmd(controller, alpha=0.0, measured=[0]).fit(trajs[:3])
    true = replace(trajs[3], state_names=("position", "velocity"))
    # What the sensor reports when its zero is off by OFFSET: the measured position and, as
    # the controller compares the reference with it, the logged reference (same tracking error).
    measured = replace(true, x=true.x + [OFFSET, 0.0], r=true.r + OFFSET)
    return model, true, measured


def test_closed_loop_offset_is_recovered_exactly_from_a_window(fitted):
    model, true, measured = fitted
    est = estimate_offsets(model.closed_loop_model_, measured, ["position"], window=100)
    assert est.channels == (0,) and est.plausible
    assert est.values[0] == pytest.approx(OFFSET, abs=1e-8)
    assert est.rms_after < 1e-8 < est.rms_before


def test_prediction_with_the_estimate_is_the_true_prediction_shifted(fitted):
    model, true, measured = fitted
    cl = model.closed_loop_model_
    with_offsets = cl.predict(measured, offsets=["position"], window=100)
    np.testing.assert_allclose(with_offsets, cl.predict(true) + [OFFSET, 0.0], atol=1e-7)
    assert r2_score(measured.x[100:], with_offsets[100:]) > 1 - 1e-10
    assert r2_score(measured.x[100:], cl.predict(measured)[100:]) < 1 - 1e-4  # the offset hurts without it
    known = cl.predict(measured, offsets={"position": OFFSET})
    np.testing.assert_allclose(known, with_offsets, atol=1e-7)


def test_plant_model_offsets_shift_history_only(fitted):
    model, true, measured = fitted
    plant = model.plant_model_
    est = estimate_offsets(plant, measured, [0], window=100)
    assert est.values[0] == pytest.approx(OFFSET, abs=1e-8)


def test_an_implausible_estimate_is_flagged_and_not_used(fitted):
    model, _, measured = fitted
    cl = model.closed_loop_model_
    with pytest.warns(OffsetWarning, match="plausibility bound"):
        pred, est = predict_estimating_offsets(cl, measured, [0], window=100, bound=0.01)
    assert not est.plausible and est.as_mapping() == {}
    np.testing.assert_array_equal(pred, cl.predict(measured))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"offsets": ["beta"], "window": 100}, "unknown channel 'beta'"),
        ({"offsets": [5], "window": 100}, "not a state index"),
        ({"offsets": [0]}, "needs window"),
        ({"offsets": [0], "window": 2}, "estimation window"),
        ({"offsets": [0, 0], "window": 100}, "repeat"),
    ],
)
def test_bad_offset_requests_name_the_problem(fitted, kwargs, message):
    model, _, measured = fitted
    with pytest.raises(ValueError, match=message):
        model.closed_loop_model_.predict(measured, **kwargs)
