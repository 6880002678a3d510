"""Benchmark: Kim & Kim Table II / Fig. 2-4 on the paper's 2D simulation.

Same as ``octolgp bench paper2d``; prints the table and writes the figures (BENCHMARKS.md,
"Kim & Kim Table II, Fig. 2–4: the paper's 2D simulation").

    python tools/bench_paper2d.py --out bench_out --repeats 5 --seeds 5
"""

from __future__ import annotations

import argparse
from pathlib import Path

from octolgp.bench.paper2d import format_table, run_paper2d


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench_out")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    result = run_paper2d(Path(args.out), seed=args.seed, repeats=args.repeats, n_seeds=args.seeds)
    print(format_table(result))


if __name__ == "__main__":
    main()
