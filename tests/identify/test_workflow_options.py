"""IdentifyOptions: identify_and_score's settings, refused together when they contradict one another."""

import pytest

from qube_koopman.core.controller import PdGains, pd_controller
from qube_koopman.identify.models.kstep import AheadOptions
from qube_koopman.identify.uncertainty import IntervalOptions
from qube_koopman.identify.workflow import FitOptions, IdentifyOptions, OffsetProtocol, OutputOptions, ScoreOptions

WHAT_IF = pd_controller(PdGains(-2.0, -0.5, 20.0, 1.0, 0.01))


@pytest.mark.parametrize(
    "fit, scoring, extra, message",
    [
        ("arx", ScoreOptions("plant", offsets=OffsetProtocol(("alpha",))), {}, "need a Koopman method, not arx"),
        ("cl-arx", ScoreOptions(), {"intervals": IntervalOptions(0.9)}, "need a Koopman method, not cl-arx"),
        ("cl-arx", ScoreOptions(), {"ahead": AheadOptions((0.1,))}, "need a Koopman method, not cl-arx"),
        ("arx", ScoreOptions("cl"), {}, "ARX models the plant only"),
        ("cl-edmd", ScoreOptions("plant", what_if=WHAT_IF), {}, "a what-if controller predicts the closed loop"),
        ("cl-edmd", ScoreOptions("plant", command_delay=1.0), {}, "a command delay changes the predicted loop"),
        ("cl-arx", ScoreOptions("cl", command_delay="estimate"), {}, "a command delay changes the predicted loop"),
        ("cl-edmd", ScoreOptions(command_delay="soon"), {}, "a number of sample periods or 'estimate', got 'soon'"),
        ("cl-edmd", ScoreOptions(command_delay=-1.0), {}, "must be 0 or more sample periods, got -1.0"),
        ("sindy", ScoreOptions(), {}, "unknown method 'sindy'"),
    ],
)
def test_contradicting_options_are_refused_when_made(fit, scoring, extra, message):
    with pytest.raises(ValueError, match=message):
        IdentifyOptions(FitOptions(fit), scoring, **extra)


def test_the_groups_default_to_the_paper_protocol_and_scored_from_the_second_sample():
    options = IdentifyOptions(FitOptions("cl-edmd"), intervals=IntervalOptions(0.9, method="disturbance"))
    assert options.scoring == ScoreOptions() and options.output == OutputOptions()
    assert options.scoring.first_scored(0.002) == 1 and options.filtered
    assert ScoreOptions(score_from=500).first_scored(0.002) == 500
    assert ScoreOptions(offsets=OffsetProtocol(("alpha",), 0.5)).first_scored(0.002) == 250
    assert not IdentifyOptions(FitOptions("cl-edmd"), intervals=IntervalOptions(0.9)).filtered
