"""Reproductions of the paper's results (``qube-reproduce``): an application above ``identify``.

``reproduce.qube`` runs the paper's QUBE-Servo study on imported logs (every method, the
regularization sweep, the eigenvalues and the table), ``reproduce.duffing`` the Duffing
oscillator's, ``reproduce.report`` and ``reproduce.figures`` write them. Nothing imports this
package; it imports ``identify``, ``daq``'s log names and ``sim``.
"""
