#!/usr/bin/env python
"""Write tests/durations.json, the seconds each test module took, from the report of a full run with durations:

    ./test.sh --durations=0 | tee /tmp/suite.log
    .venv/bin/python scripts/test_durations.py /tmp/suite.log

tests/conftest.py runs the modules longest first from it (those not in it by an estimate from their markers), so
that xdist's workers start the long modules early and finish on the short ones.
"""

from __future__ import annotations

import json
import re
import sys
from collections import defaultdict
from pathlib import Path

LINE = re.compile(r"^\s*([\d.]+)s (?:setup|call|teardown)\s+(tests/[\w/]+\.py)::")


def module_seconds(report: str) -> dict[str, float]:
    seconds: dict[str, float] = defaultdict(float)
    for line in report.splitlines():
        m = LINE.match(line)
        if m:
            seconds[m.group(2)] += float(m.group(1))
    return {name: round(s, 1) for name, s in sorted(seconds.items(), key=lambda kv: -kv[1])}


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    seconds = module_seconds(Path(sys.argv[1]).read_text())
    if not seconds:
        print(f"no durations in {sys.argv[1]}: run the suite with --durations=0", file=sys.stderr)
        return 1
    out = Path(__file__).resolve().parents[1] / "tests" / "durations.json"
    out.write_text(json.dumps(seconds, indent=1) + "\n")
    print(f"{out}: {len(seconds)} modules, {sum(seconds.values()):.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
