"""Controller design from identified plant models (``qube-design``).

The package above ``identify``: it reads a model file, designs a controller (an LQ state
feedback on the plant's history with integral action on the arm), predicts the closed loop
it gives on the rig's excitation, and writes it as a state-space controller file that
``qube-run --controller`` runs. Imports go one way: ``design`` uses ``identify``, ``daq`` and
``sim``; none of them imports ``design``.
"""

from qube_koopman.design.lq import LqDesign, Weights, augment, design_lq, realize
from qube_koopman.design.plant import DesignError, LinearPlant, linear_plant

__all__ = ["DesignError", "LinearPlant", "linear_plant", "Weights", "LqDesign", "augment", "design_lq", "realize"]
