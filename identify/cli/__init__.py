"""Command-line entry points (heavy imports happen inside ``main``)."""
