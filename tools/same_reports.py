#!/usr/bin/env python
"""Compare two runs' JSON outputs (report.json, model.json, ...), ignoring timings.

    python tools/same_reports.py BEFORE_DIR AFTER_DIR [--ignore WORD ...]

Every ``*.json`` file in BEFORE_DIR is compared with the file of the same name in AFTER_DIR:
the same keys in the same order and the same values, except under keys containing
"seconds", "timing", "created" or "elapsed" (and any ``--ignore`` word), and the run's own
folder names (BEFORE_DIR's path replaced by AFTER_DIR's). Prints each difference with its
path in the document; exits 1 when any is found or a file is missing.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

IGNORED = ("seconds", "timing", "created", "elapsed")


def differences(before, after, ignored=IGNORED, where: str = "") -> list[str]:
    """Where ``before`` and ``after`` (parsed JSON) differ, keys containing an ``ignored`` word skipped."""
    if isinstance(before, dict) and isinstance(after, dict):
        keep = [k for k in before if not any(w in k for w in ignored)]
        other = [k for k in after if not any(w in k for w in ignored)]
        if keep != other:
            return [f"{where or '/'}: keys {keep} != {other}"]
        return [d for k in keep for d in differences(before[k], after[k], ignored, f"{where}/{k}")]
    if isinstance(before, list) and isinstance(after, list):
        if len(before) != len(after):
            return [f"{where}: {len(before)} items != {len(after)}"]
        return [d for i, (b, a) in enumerate(zip(before, after)) for d in differences(b, a, ignored, f"{where}/{i}")]
    if type(before) is float and type(after) is float and math.isnan(before) and math.isnan(after):
        return []  # NaN (json's NaN) on both sides: the same value
    return [] if before == after and type(before) is type(after) else [f"{where}: {before!r} != {after!r}"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--ignore", nargs="*", default=[], help="more words: keys containing one are skipped")
    args = parser.parse_args(argv)
    ignored = (*IGNORED, *args.ignore)
    found, n = [], 0
    for path in sorted(args.before.glob("*.json")):
        other = args.after / path.name
        if not other.exists():
            found.append(f"{other}: missing")
            continue
        text = path.read_text().replace(str(args.before.resolve()), "<out>").replace(str(args.before), "<out>")
        after = other.read_text().replace(str(args.after.resolve()), "<out>").replace(str(args.after), "<out>")
        found += [f"{path.name}{d}" for d in differences(json.loads(text), json.loads(after), ignored)]
        n += 1
    for line in found:
        print(line)
    print(f"{n} file(s) compared, {len(found)} difference(s)")
    return 1 if found or n == 0 else 0


if __name__ == "__main__":
    sys.exit(main())
