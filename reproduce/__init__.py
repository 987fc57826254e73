"""Reproductions of the paper's results."""
