"""The host side of an experiment on the QUBE-Servo: acquisition, logs and their formats.

``daq`` owns what runs and records an episode: backends (``daq.backends``:
the simulated pendulum and the serial bridge), the controller built from
gains (``daq.controller``), the rig's excitation (``daq.excitation``), the
500 Hz loop with its safety supervisor and timing statistics (``daq.loop``,
``daq.safety``, ``daq.timing``), the episode and its metadata
(``daq.episode``, with ``stack_signals``), the MCAP episode log (``daq.log``, format in
``daq/log/FORMAT.md``; file names in ``daq.log.names``), legacy CSV import (``daq.legacy_csv``), export to
CSV, Parquet and MATLAB (``daq.export``) and the live rerun view
(``daq.viz``). Start with ``daq.session.run_episodes`` (what ``qube-run``
calls) to acquire, and ``daq.log.read_episode`` to read a log back.
Imports only ``firmware_protocol`` and ``sim`` from this project.
"""
