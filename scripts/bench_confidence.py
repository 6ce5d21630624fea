"""Score the ``confident`` flag over several benchmark results: pooled, then per pair source.

    python scripts/bench_confidence.py outputs/benchmark/fragments/<run>/results.json \\
        outputs/benchmark/3dmatch/<run>/results.json outputs/benchmark/human/<run>/results.json

Each record of ``linereg-benchmark``'s ``results.json`` carries ``confident``
(:func:`linereg.registration.api.quality`); it is scored against *correct* = RRE <= 2 deg and
RTE <= 2 % of the target's bounding-box diagonal
(:func:`linereg.registration.benchmark_results.confidence_lines`): TP/FP/FN/TN, precision and
recall per method and over all records, then per source.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", type=Path, help="results.json files of linereg-benchmark")
    args = parser.parse_args(argv)
    from linereg.registration.benchmark_results import confidence_lines, pooled_records

    print("\n".join(confidence_lines(pooled_records(args.results), "pairs")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
