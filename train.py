"""Train DeepLabv3+ (default: procedural street scenes). See `python train.py --help`."""

from costseg.cli import train_main

if __name__ == "__main__":
    train_main()
