"""MI estimator accuracy and speed against ground truth; prints a markdown table.

    .venv/bin/python benchmarks/mi_accuracy.py                      # full size (a few minutes)
    .venv/bin/python benchmarks/mi_accuracy.py --count=50 --sizes 100
    .venv/bin/python benchmarks/mi_accuracy.py --infonet_weights=outputs/infonet/final  # retrained weights

Test distributions are fresh random 2-D Gaussian mixtures (1-10 components; Monte-Carlo MI from
exact densities) and bivariate Gaussians with rho ~ U(-0.95, 0.95) (closed-form MI).
"""

import argparse
import json
import os
import platform
from dataclasses import asdict

import torch

from lerobot_maxmi.mi import ESTIMATORS
from lerobot_maxmi.mi.evaluate import FAMILIES, TEST_SEED, evaluate_estimators, format_table


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), choices=list(ESTIMATORS))
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(FAMILIES))
    parser.add_argument("--sizes", nargs="+", type=int, default=[100, 1000])
    parser.add_argument("--count", type=int, default=200, help="test distributions per family and size")
    parser.add_argument("--mc_samples", type=int, default=100_000, help="Monte-Carlo samples per GMM")
    parser.add_argument("--seed", type=int, default=TEST_SEED)
    parser.add_argument("--json", help="also write the rows to this JSON file")
    parser.add_argument(
        "--infonet_weights", help="InfoNet directory or hub repo id to score instead of the shipped weights"
    )
    args = parser.parse_args()
    rows = evaluate_estimators(
        args.estimators,
        args.families,
        args.sizes,
        args.count,
        args.seed,
        args.mc_samples,
        args.infonet_weights,
    )
    print(
        f"\n{args.count} distributions per row; torch threads: {torch.get_num_threads()}; "
        f"{platform.machine()} {os.cpu_count()} cores"
    )
    print(format_table(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump([asdict(r) for r in rows], f, indent=2)


if __name__ == "__main__":
    main()
