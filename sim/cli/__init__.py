"""Command-line tools of the ``sim`` package (``qube-emulate``)."""
