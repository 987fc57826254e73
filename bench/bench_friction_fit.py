"""An experiment: ``qube-calibrate`` with the arm friction's shape fitted too (static friction, the
Coulomb sign's sharpness), to see whether the shape the short segments find moves the twin's bands.

    python bench/bench_friction_fit.py [--free Cs,coulomb_speed] QUBE-CALIBRATE ARGUMENTS...

Runs ``qube-calibrate`` with its arguments in this process after appending the ``--free``
parameters to the fitted table (:data:`qube_koopman.identify.calibrate.shooting.PHYSICAL`):
``Cs`` (static friction beyond ``Cr``, N m, from 0), ``coulomb_speed`` and ``stribeck_speed``
(rad/s, each 1/50 to 2 times and 1/10 to 10 times its nominal). ``--free ''`` runs the table as
shipped. The tool's own fit does not free them: measured below, the bands the twin is judged on do
not move. Then replay the plant with ``bench/bench_random_load.py`` (held out) and
``bench/bench_slow_bands.py`` (where the slow power sits, how long the arm holds still).

Measured (``--setups cables-and-delay --horizon 0.25 --load --tilt --max-nfev 150``, the recipe of
``calibrated-with-load``):

- On its 38 logs: with ``Cs`` freed (``stribeck_speed`` 0.1, ``coulomb_speed`` 0.05 held), ``Cs``
  0.429e-3 +- 0.005e-3 N m and ``Cr`` 0.344e-3 (0.402e-3 without), residual RMS theta / alpha
  2.432 / 2.058 mrad against 2.446 / 2.069. With ``coulomb_speed`` freed too, 0.0110 +- 0.0005 rad/s,
  ``Cs`` 0.184e-3, ``Cr`` 0.351e-3, residuals 2.426 / 2.049. With ``stribeck_speed`` as well the
  fit had not converged after 150 steps (``Cs`` 1.3e-3 fading over 0.038 rad/s, the two traded
  against each other).
- ``bench_slow_bands.py`` on the soft episodes (4 draws), the voltage from 0.1 to 0.3 Hz and the
  share of time the arm holds still for 0.4 s or more: 0.758 and 0.9 % without, 0.761 and 1.6 %
  with ``Cs``, 0.776 and 1.9 % with ``Cs`` and ``coulomb_speed`` (real: 3.8 %), 0.790 and 2.1 %
  with all three.
- Held out (the 28 rig logs and soft episodes 1-3, 6-8 fitted; ``bench_random_load.py --draws 8``,
  load + tilt, theta / alpha / voltage below 0.3 Hz): the rig's 20 test episodes 0.992 / 0.946 /
  0.908 without, 0.991 / 0.944 / 0.903 with ``Cs`` and ``coulomb_speed``; soft episodes 4, 5, 9,
  10 0.947 / 0.948 / 0.808 and 0.950 / 0.943 / 0.805. Every other band within 0.01 of the other's.

The segments see the friction (its standard errors are 2-5 % of it, the residuals about 1 % smaller)
and the arm sticks more like the rig's, but the held-out bands, the soft controller's slow voltage
among them, do not move.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

#: The rows ``--free`` may append to the fitted table: (name, kind, scale, lower, upper), as
#: ``shooting.PHYSICAL``'s ("log": bounds on the logarithm of the ratio to the nominal).
ROWS = {
    "Cs": ("Cs", "linear", 1e-4, 0.0, 100.0),
    "coulomb_speed": ("coulomb_speed", "log", 1.0, np.log(0.02), np.log(2.0)),
    "stribeck_speed": ("stribeck_speed", "log", 1.0, np.log(0.1), np.log(10.0)),
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], add_help=True)
    p.add_argument("--free", default="Cs,coulomb_speed", help="comma-separated: " + ", ".join(ROWS))
    args, rest = p.parse_known_args(argv)
    names = [n for n in args.free.split(",") if n]
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        print(f"bench_friction_fit: --free: unknown {', '.join(unknown)} (one of {', '.join(ROWS)})", file=sys.stderr)
        return 2
    from qube_koopman.identify.calibrate import shooting
    from qube_koopman.identify.cli.calibrate import main as calibrate

    # The solver, the tangents and the report read the table through the module at every call.
    shooting.PHYSICAL = shooting.PHYSICAL + tuple(ROWS[n] for n in names)
    shooting.PHYSICAL_NAMES = tuple(row[0] for row in shooting.PHYSICAL)
    shooting.N_PHYSICAL = len(shooting.PHYSICAL)
    return calibrate(rest)


if __name__ == "__main__":
    sys.exit(main())
