"""Reproductions of the paper's results (``qube-reproduce``): an application above ``identify``.

``reproduce.qube_study`` runs the paper's QUBE-Servo study on imported logs (every method, the
regularization sweep, the eigenvalues and the table), ``reproduce.duffing_study`` the Duffing
oscillator's, ``reproduce.qube_tables`` and ``reproduce.qube_figures`` write them. Nothing imports this
package; it imports ``identify``, ``daq``'s log names and ``sim``.
"""
