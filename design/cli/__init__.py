"""The command-line tool of the design package: ``qube-design``."""
