"""Command-line entry points of the daq package (each imports its heavy parts lazily)."""
