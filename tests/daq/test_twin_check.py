"""A controller file is checked on the twin's linearized loop before qube-run runs it: refused on the rig when the
loop diverges (unless --run-unstable), a warning on the simulator; the shipped controllers pass."""

import pytest

from qube_koopman.core import PdGains, load_pd_gains, pd_controller
from qube_koopman.core.command import CliError
from qube_koopman.daq.twin_check import check_controller_on_twin
from qube_koopman.sim import PendulumParameters, linear_loop_radius

UNSTABLE = {
    "gains reversed": PdGains(-6.0, -1.8, -30.0, -2.5, 50.0),
    "pendulum loop too weak": PdGains(6.0, 1.8, 10.0, 0.5, 50.0),
    "no pendulum damping": PdGains(6.0, 1.8, 30.0, 0.2, 50.0),
}


@pytest.mark.parametrize("name", ["rig", "soft-theta"])
def test_the_shipped_controllers_balance_the_twin(name):
    controller = pd_controller(load_pd_gains(name))
    assert linear_loop_radius(controller) < 0.995  # measured 0.9919 (rig) and 0.9934 (soft-theta)
    for backend in ("serial", "sim"):
        assert check_controller_on_twin(controller, f"{name}.toml", backend) is None


@pytest.mark.parametrize("gains", list(UNSTABLE.values()), ids=list(UNSTABLE))
def test_a_diverging_controller_is_refused_on_the_rig_and_a_warning_on_the_simulator(gains):
    controller = pd_controller(gains)
    radius = linear_loop_radius(controller)
    assert radius > 1.03  # measured 1.035 to 1.079
    with pytest.raises(CliError) as caught:
        check_controller_on_twin(controller, "bad.toml", "serial")
    message = str(caught.value)
    assert message.startswith(
        "bad.toml: the controller destabilises the twin's loop linearized at upright "
        f"(spectral radius {radius:.4f} > 1): refused on the rig; --run-unstable runs it anyway"
    )
    assert caught.value.status == 2 and "\n" not in message
    assert check_controller_on_twin(controller, "bad.toml", "sim").startswith("bad.toml: the controller destabilises")
    assert "as --run-unstable asks" in check_controller_on_twin(controller, "bad.toml", "serial", run_unstable=True)


def test_the_linearized_loop_leaves_the_coulomb_slope_out_and_checks_shapes():
    import dataclasses

    rig = pd_controller(load_pd_gains("rig"))
    twin = PendulumParameters()
    # the Coulomb torque's slope at rest taken as damping would call the rig's own PD unstable
    assert linear_loop_radius(rig, dataclasses.replace(twin, Cr=0.0)) == pytest.approx(linear_loop_radius(rig, twin))
    with pytest.raises(ValueError, match="takes 1 inputs"):
        from qube_koopman.core.lti import DiscreteStateSpace

        linear_loop_radius(DiscreteStateSpace([[0.0]], [[0.0]], [[0.0]], [[1.0]], 0.002))
