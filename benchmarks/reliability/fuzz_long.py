"""The long fuzz run (issue 31): the property tests of tests/package/test_fuzz.py with many random examples.

    python benchmarks/reliability/fuzz_long.py --examples 2000          # ~10-20 minutes on a quiet 2-core machine
    python benchmarks/reliability/fuzz_long.py --examples 200 --seeded  # the default suite's fixed seed, more examples

Prints, per target (PLY, trajectory, intrinsics, --set, config, manifest, image headers, CLI export), how many
generated inputs were accepted and how many refused with one line; exits non-zero when any property failed.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--examples", type=int, default=2000, help="examples per property test")
    ap.add_argument("--seeded", action="store_true", help="derandomised (the default suite's fixed seed)")
    ap.add_argument("-k", default=None, help="pytest -k expression: only some targets")
    args = ap.parse_args(argv)
    os.environ["ELIGSIR_FUZZ_EXAMPLES"] = str(args.examples)
    os.environ["ELIGSIR_FUZZ_RANDOM"] = "0" if args.seeded else "1"
    import pytest

    t0 = time.perf_counter()
    extra = ["-k", args.k] if args.k else []
    code = pytest.main([str(ROOT / "tests" / "package" / "test_fuzz.py"), "-q", "-p", "no:cacheprovider", *extra])
    wall = time.perf_counter() - t0
    mod = next((m for name, m in sys.modules.items() if name.endswith("test_fuzz") and hasattr(m, "COUNTS")), None)
    counts = getattr(mod, "COUNTS", {})
    total = 0
    print(f"\nfuzz: {args.examples} examples per property, {'seeded' if args.seeded else 'random'}, "
          f"{wall:.0f} s, pytest exit {int(code)}")
    for target, (ok, refused) in sorted(counts.items()):
        total += ok + refused
        print(f"  {target:12s} accepted {ok:6d}  refused with one line {refused:6d}")
    print(f"  {'total':12s} {total} inputs")
    return int(code)


if __name__ == "__main__":
    raise SystemExit(main())
