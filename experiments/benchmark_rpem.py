"""Throughput of the compiled RPEM recursion (samples per second on one core, after JIT warm-up): the figures of
:func:`ident.speed.measure_rpem_speed` (its docstring says what each one times).

    python -m experiments.benchmark_rpem [--samples 200000] [--json PATH]
"""
from __future__ import annotations

import argparse
from collections.abc import Sequence

from experiments._runs import write_json
from ident.speed import measure_rpem_speed
from scr_env.fileio import check_output_file


def main(argv: Sequence[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description="RPEM throughput benchmark")
    ap.add_argument("--samples", type=int, default=200_000, help="samples per timed pass")
    ap.add_argument("--json", type=str, default=None, help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    if args.json:
        check_output_file(args.json, "--json file")
    result = measure_rpem_speed(args.samples)
    for key, val in result.items():
        print(f"{key}: {val:,.0f}")
    if args.json:
        write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
