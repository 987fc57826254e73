"""The command-line tool of the reproduce package: ``qube-reproduce``."""
