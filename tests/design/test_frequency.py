"""``qube-design --figures DIR``: Bode plots of the plant, the controller and the loop, and the loop's margins.

The margins the figure's title gives (the PNG's ``Title``, and the command's report) are python-control's
``stability_margins`` of the loop built here by python-control from the controller file and the model's plant
(``K * P`` of their state spaces, on the same frequency grid): not the loop the figures computed. The loop of
this design has a phase crossing exactly at the Nyquist frequency, which no sign change on the grid marks: its gain
margin, the smallest upward one, is added to python-control's.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from test_design_uncertainty import _plant, _save

from qube_koopman.core.controller_file import load_controller
from qube_koopman.design import linear_plant
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.frequency import frequency_grid

NUMBER = r"([-+]?(?:\d+\.\d+|inf))"


def _title_margins(title: str) -> tuple[float, ...]:
    match = re.fullmatch(
        rf"loop at the plant input: gain margin \+?{NUMBER} dB / {NUMBER} dB, phase margin {NUMBER} deg at "
        rf"{NUMBER} Hz, min\|1 \+ L\| {NUMBER}",
        title,
    )
    assert match, title
    return tuple(float(v) for v in match.groups())


def test_the_figures_are_written_and_their_margins_are_python_controls_of_the_same_loop(tmp_path, capsys):
    import control
    from PIL import Image

    model = _save(tmp_path / "model.json", _plant())
    out = tmp_path / "designed.toml"
    figures = tmp_path / "figures"  # created
    argv = [str(model), "--out", str(out), "--episodes", "2", "--duration", "4", "--figures", str(figures)]
    assert design_main(argv) == 0
    text = capsys.readouterr().out
    bode, margins = figures / "designed_bode.png", figures / "designed_margins.png"
    assert f"wrote {bode} (Bode plots of the plant, the controller and the loop) and {margins}" in text
    with Image.open(bode) as image:
        assert (
            image.size == (900, 700) and "Bode plots of the plant, the controller and the loop" in image.text["Title"]
        )
    with Image.open(margins) as image:
        title = image.text["Title"]
    up, down, phase, where, stability = _title_margins(title)

    plant = linear_plant(_plant())
    controller = load_controller(out).system
    loop = controller.to_control() * plant.to_control()  # K P: voltage in, voltage out, python-control's own
    omega = frequency_grid(plant.dt)
    gm, pm, _, _, wpm, _ = control.stability_margins(control.frd(loop, omega), returnall=True)
    gm, pm, wpm = np.atleast_1d(gm), np.atleast_1d(pm), np.atleast_1d(wpm)
    # A phase crossing exactly at the Nyquist frequency, where a discrete loop's response is real, is one no sign
    # change marks on the grid, so stability_margins does not see it: its gain margin is 1 / |L| there.
    at_nyquist = loop(np.exp(1j * np.pi))
    assert at_nyquist.real < 0 and abs(at_nyquist.imag) < 1e-9  # this design's loop has one
    gm = np.append(gm, 1 / abs(at_nyquist.real))
    assert len(gm[gm > 1]) and len(gm[gm < 1]) and len(pm), "an unstable plant: margins up and down, a phase crossing"
    assert up == pytest.approx(20 * np.log10(gm[gm > 1].min()), abs=0.006)
    assert down == pytest.approx(20 * np.log10(gm[gm < 1].max()), abs=0.006)
    i = np.argmin(np.abs(pm))
    assert phase == pytest.approx(pm[i], abs=0.006) and where == pytest.approx(wpm[i] / (2 * np.pi), abs=6e-4)
    response = loop(np.exp(1j * omega * plant.dt))
    assert stability == pytest.approx(np.min(np.abs(1 + response)), abs=6e-4)
    # the report's margins line says the same, at its own precision
    printed = re.search(r"margins at the plant input: gain \+([\d.]+) dB / ([-\d.]+) dB, phase ([-\d.]+) deg", text)
    assert [float(v) for v in printed.groups()] == pytest.approx([up, down, phase], abs=0.06)

    again = tmp_path / "again" / "designed.toml"  # another controller file of that name: its figures' names taken
    again.parent.mkdir()
    argv[2] = str(again)
    assert design_main(argv) == 2  # refused before any work, unless --force
    assert capsys.readouterr().err == (
        f"qube-design: error: {figures / 'designed_bode.png'}: exists (use --force to overwrite) (--figures)\n"
    )
    assert not again.exists()
