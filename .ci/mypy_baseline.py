"""mypy against a committed baseline that may only shrink.

Runs mypy on ``src/hallcal`` (settings in pyproject.toml), counts the errors per file and
compares them with ``.ci/mypy-baseline.json``. It fails when a file has more errors than its
baseline entry (a file absent from the baseline has a baseline of 0), so new code is typed and
old errors are only ever removed. ``--update`` rewrites the baseline from the current counts
(run it after fixing errors, never to admit new ones: the diff of the baseline shows which).

The numeric core (``src/hallcal/{sim,fit,sensor,identify}``, type-checked with
``check_untyped_defs``) is strict: any error there fails, whatever the baseline says, and
``--update`` refuses to write a baseline that admits one.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BASELINE = ROOT / ".ci" / "mypy-baseline.json"
LINE = re.compile(r"^(src/hallcal/[^:]+\.py):\d+(?::\d+)?: error: ")
STRICT = tuple(f"src/hallcal/{pkg}/" for pkg in ("sim", "fit", "sensor", "identify"))


def current_counts() -> Counter[str]:
    out = subprocess.run(
        [sys.executable, "-m", "mypy", "src/hallcal", "--no-error-summary"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode not in (0, 1):  # 2: mypy itself failed (bad config, crash)
        sys.stderr.write(out.stdout + out.stderr)
        raise SystemExit(2)
    counts: Counter[str] = Counter()
    for line in out.stdout.splitlines():
        m = LINE.match(line)
        if m:
            counts[m.group(1)] += 1
    return counts


def main(argv: list[str]) -> int:
    counts = current_counts()
    strict = {f: n for f, n in counts.items() if f.startswith(STRICT)}
    for f, n in sorted(strict.items()):
        print(f"{f}: {n} mypy errors in the numeric core (must be 0)")
    if strict:
        print(
            f"mypy: {sum(strict.values())} errors in the numeric core (sim, fit, sensor, "
            "identify), which has no baseline (python -m mypy src/hallcal shows them)"
        )
        return 1
    if "--update" in argv:
        BASELINE.write_text(json.dumps(dict(sorted(counts.items())), indent=1) + "\n")
        print(f"mypy baseline: {sum(counts.values())} errors in {len(counts)} files")
        return 0
    baseline: dict[str, int] = json.loads(BASELINE.read_text()) if BASELINE.exists() else {}
    worse = {f: (n, baseline.get(f, 0)) for f, n in counts.items() if n > baseline.get(f, 0)}
    total, allowed = sum(counts.values()), sum(baseline.values())
    for f, (n, b) in sorted(worse.items()):
        print(f"{f}: {n} mypy errors, baseline {b}")
    if worse:
        print(
            f"mypy: {len(worse)} files above their baseline (python -m mypy src/hallcal shows them)"
        )
        return 1
    print(f"mypy: {total} errors, baseline {allowed} (.ci/mypy-baseline.json)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
