"""Apply cost-based decision rules to your own images or videos. See `python predict.py --help`."""

from costseg.cli import predict_main

if __name__ == "__main__":
    predict_main()
