"""`make demo`: the embedded default job, small enough for a laptop CPU.

At this stage it measures the shipped MI estimators against ground truth and prints the table
(a scaled-down `benchmarks/mi_accuracy.py`).
"""

from lerobot_maxmi.mi import ESTIMATORS
from lerobot_maxmi.mi.evaluate import FAMILIES, evaluate_estimators, format_table


def main() -> None:
    rows = evaluate_estimators(
        list(ESTIMATORS), list(FAMILIES), sizes=[100, 1000], count=50, seed=7, mc_samples=50_000
    )
    print("\nMI estimators vs ground truth (50 fresh distributions per row):")
    print(format_table(rows))


if __name__ == "__main__":
    main()
