"""Evaluate a checkpoint under cost-based decision rules. See `python evaluate.py --help`."""

from costseg.cli import evaluate_main

if __name__ == "__main__":
    evaluate_main()
