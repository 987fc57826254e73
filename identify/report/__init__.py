"""What an identification run shows: report.md / report.json text, figures (matplotlib),
and rerun recordings.
"""
