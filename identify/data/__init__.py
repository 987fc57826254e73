"""Identification data: trajectories, and reading episode logs as trajectories.

The only part of ``identify`` that reads ``daq``'s episode logs.
"""
