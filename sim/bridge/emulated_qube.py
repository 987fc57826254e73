"""The QUBE-Servo 2 behind its SPI interface, over the simulated pendulum.

The bridge firmware talks to the QUBE in one 17-byte full-duplex transfer
per tick (``firmware_protocol.qube_spi``): it writes the motor word, LEDs and
encoder presets and reads back the module id, both encoder counters, the
status byte and the current sense of that same moment. :class:`EmulatedQube`
answers such transfers from :class:`~sim.pendulum.PendulumSimulator`:

- the counters are the pendulum's true angles to the nearest count, the
  pendulum's zeroed hanging down (:func:`~sim.pendulum.sensor.angles_to_counts`),
  as the rig's were;
- the motor word takes effect at the transfer and is held until the next
  one (:meth:`EmulatedQube.advance` integrates over that period); bit 15
  enables the amplifier, bits 14-0 are PWM counts of 24 mV;
- an amplifier fault or stall error (injected: the emulator does not model
  their physical causes) drives the motor at 0 V and sets its status bit
  until a word with bit 15 clear arrives, as the QUBE clears a stall error;
- current sense follows the armature, ``I = (V - km theta_dot) / Rm``; the
  tachometer word is not emulated (always 0: protocol version 1 defines no
  conversion for it).
"""

from __future__ import annotations

from qube_koopman.firmware_protocol.messages import MODULE_ID_QUBE_SERVO_2
from qube_koopman.firmware_protocol.qube_spi import (
    MASK_ENCODER0,
    MASK_ENCODER1,
    MILLIVOLTS_PER_PWM,
    MOTOR_ENABLE,
    SpiResponse,
    pack_spi_response,
    unpack_spi_command,
)
from qube_koopman.sim.pendulum import PendulumParameters, PendulumSimulator, SensorModel
from qube_koopman.sim.pendulum.load import RandomLoad
from qube_koopman.sim.pendulum.relaxation import CableRelaxation
from qube_koopman.sim.pendulum.physics import SAMPLE_PERIOD
from qube_koopman.sim.pendulum.sensor import angles_to_counts

__all__ = ["EmulatedQube", "STATUS_AMP_FAULT", "STATUS_STALL_ERROR", "current_raw"]

STATUS_AMP_FAULT = 0x01
STATUS_STALL_ERROR = 0x04
# Quanser's scaling: +-999 PWM counts is +-100 % of 24 V.
_PWM_LIMIT = 999


def current_raw(amps: float) -> int:
    """The raw current-sense word for a current: inverse of ``(3.3 / (4 * 4095)) (raw / 2 - 4095)``."""
    raw = round(2.0 * (amps * 4 * 4095 / 3.3 + 4095))
    return min(max(raw, 0), 0xFFFF)


class EmulatedQube:
    """A QUBE-Servo 2 answering SPI transfers from a simulated pendulum.

    Parameters
    ----------
    params : PendulumParameters
        Physical model.
    dt : float
        Time between transfers (s): the bridge's tick period.
    module_id : int
        The id returned over SPI (777 for a QUBE-Servo 2; anything else makes
        the firmware report the QUBE absent).
    load : RandomLoad, optional
        A random torque on the arm (a plant file's ``[load]``); :meth:`place` with a
        ``load_seed`` starts a new draw of it. None: none.
    relaxation : CableRelaxation, optional
        The cables' torque that the arm's motion drives (a plant file's ``[relaxation]``); None: none.
    """

    def __init__(
        self,
        params: PendulumParameters = PendulumParameters(),
        dt: float = SAMPLE_PERIOD,
        module_id: int = MODULE_ID_QUBE_SERVO_2,
        load: RandomLoad | None = None,
        relaxation: CableRelaxation | None = None,
    ) -> None:
        self.params = params
        self.module_id = module_id
        self.load = load
        # Exact angles: the counters quantize, once, in transfer().
        self._sim = PendulumSimulator(params, SensorModel(counts_per_rev=None), dt=dt, load=load, relaxation=relaxation)
        self._offsets = [0, 0]
        self.volts = 0.0
        self.enabled = False
        self.amp_fault = False
        self.stall_error = False
        self.led = (0, 0, 0)
        self._latched_raw = (0, 0)

    @property
    def dt(self) -> float:
        """Seconds between transfers."""
        return self._sim.dt

    def set_period(self, dt: float) -> None:
        """Change the time between transfers (the bridge's rate was reconfigured); keeps the state."""
        if dt != self._sim.dt:
            self._sim.set_period(dt)  # the commands in flight (transport delay) carry over

    def place(self, state=(0.0, 0.0, 0.0, 0.0), load_seed: int | None = None) -> None:
        """Put the pendulum in ``state`` (theta, alpha, theta_dot, alpha_dot), counters as at power-up.

        ``load_seed``: with a load, the seed of its new draw from here on (None: the current seed's
        draw, restarted).
        """
        self._sim.reset(state, load_seed=load_seed)
        self._offsets = [0, 0]

    @property
    def state(self) -> tuple[float, float, float, float]:
        """True state (theta, alpha, theta_dot, alpha_dot); alpha = 0 upright, not wrapped."""
        return tuple(self._sim.state.tolist())

    def transfer(self, spi_tx: bytes) -> bytes:
        """One SPI transaction: apply the bridge's 17 bytes, return the QUBE's 17.

        The returned counts and current are those of this moment; the motor
        word applies from now until the next transfer.
        """
        response = self.latch()
        self.apply(spi_tx)
        return response

    def latch(self) -> bytes:
        """The QUBE's 17 bytes of this moment (chip select falling); see :meth:`apply`."""
        theta, alpha, theta_dot, _ = self._sim.state.tolist()
        raw0, raw1 = angles_to_counts(theta, alpha)
        self._latched_raw = (raw0, raw1)
        counts = (raw0 - self._offsets[0], raw1 - self._offsets[1])
        status = (STATUS_AMP_FAULT if self.amp_fault else 0) | (STATUS_STALL_ERROR if self.stall_error else 0)
        amps = (self.volts - self.params.km * theta_dot) / self.params.Rm if self.volts else 0.0
        return pack_spi_response(SpiResponse(self.module_id, counts[0], counts[1], 0, status, current_raw(amps)))

    def apply(self, spi_tx: bytes) -> None:
        """Take the bridge's 17 bytes of the transaction begun by :meth:`latch` (chip select rising)."""
        cmd = unpack_spi_command(spi_tx)
        raw0, raw1 = self._latched_raw
        # Presets take effect after this transfer's counts were latched (PROTOCOL.md, ENCODER_RESET).
        if cmd.write_mask & MASK_ENCODER0:
            self._offsets[0] = raw0 - cmd.encoder0_preset
        if cmd.write_mask & MASK_ENCODER1:
            self._offsets[1] = raw1 - cmd.encoder1_preset
        self.led = (cmd.led_red, cmd.led_green, cmd.led_blue)
        self.enabled = bool(cmd.motor & MOTOR_ENABLE)
        if not self.enabled:
            self.amp_fault = self.stall_error = False
        pwm = ((cmd.motor & 0x7FFF) ^ 0x4000) - 0x4000
        pwm = max(-_PWM_LIMIT, min(_PWM_LIMIT, pwm))
        driving = self.enabled and not (self.amp_fault or self.stall_error)
        self.volts = pwm * MILLIVOLTS_PER_PWM / 1000.0 if driving else 0.0

    def advance(self) -> None:
        """Hold the motor voltage for one period."""
        self._sim.step(self.volts)
