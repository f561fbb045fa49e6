"""What an option's text may be: the value types the command lines parse with, and the few
checks of a value the layers below them share (a grid step 1/n, the ``--network`` forms).

Plain Python, no costseg import and nothing heavy: :mod:`costseg.options` declares the options
with these types, and :mod:`costseg.costs`, :mod:`costseg.rules` and :mod:`costseg.networks`
check their own arguments with them without importing the command line's options.

>>> whole_number(1)("3"), steps_per_unit(0.25)
(3, 4)
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

NETWORK_SPECS = {
    "costseg": "PATH",
    "vainf": "PATH[?os=8|16&backbone=resnet50|resnet101]",
    "hf": "DIR",
    "segformer": "DIR",
    "onnx": "FILE[?mean=R,G,B&std=R,G,B&output=probs]",
}
"""The ``--network`` sources, ``prefix: what follows it`` (read before torch is imported, for
``--help``); :data:`costseg.networks.LOADERS` holds each one's loader under the same prefix."""
NETWORK_USAGE = ", ".join(f"{prefix}:{rest}" for prefix, rest in NETWORK_SPECS.items())


def whole_number(minimum: int) -> Callable[[str], int]:
    """Value type: an integer >= ``minimum``.

    >>> whole_number(1)("3"), whole_number(0).__name__
    (3, 'integer >= 0')
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            shown = repr(text) if value is None else value
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {shown}")
        return value

    parse.__name__ = f"integer >= {minimum}"
    return parse


def steps_per_unit(step: float, what: str = "step") -> int:
    """n for a grid step ``step`` = 1/n with n a whole number >= 1; ValueError otherwise.

    >>> steps_per_unit(0.1), steps_per_unit(0.05)
    (10, 20)
    """
    n = round(1 / step) if 0 < step <= 1 else 0
    if n < 1 or not math.isclose(n * step, 1.0, rel_tol=1e-9):
        raise ValueError(f"{what} must be 1/n for a whole number n >= 1, got {step}")
    return n


def step_size(text: str) -> float:
    """Value type: a grid step 1/n in (0, 1].

    >>> step_size("0.25")
    0.25
    """
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a step such as 0.1, got {text!r}") from None
    try:
        steps_per_unit(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a step 1/n in (0, 1], e.g. 0.1, got {text}"
        ) from None
    return value


def number_above(
    minimum: float, inclusive: bool, what: str, example: str
) -> Callable[[str], float]:
    """Value type: a finite number > ``minimum`` (>= with ``inclusive``), called ``what``.

    >>> number_above(0, True, "a defer cost", "0.3")("0")
    0.0
    """
    sign = ">=" if inclusive else ">"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not ((value >= minimum if inclusive else value > minimum) and value < math.inf):
            raise argparse.ArgumentTypeError(
                f"expected {what} {sign} {minimum:g} such as {example}, got {text!r}"
            )
        return value

    parse.__name__ = f"number {sign} {minimum:g}"
    return parse


def fraction(text: str) -> float:
    """Value type: a number in (0, 1).

    >>> fraction("0.05")
    0.05
    """
    value = number_above(0, False, "a number", "0.1")(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1) such as 0.1, got {text!r}")
    return value


fraction.__name__ = "number in (0, 1)"


def share(text: str) -> float:
    """Value type: a share in (0, 1] (1: all of it).

    >>> share("1"), share("0.25")
    (1.0, 0.25)
    """
    value = number_above(0, False, "a share", "0.5")(text)
    if value > 1:
        raise argparse.ArgumentTypeError(f"expected a share in (0, 1] such as 0.5, got {text!r}")
    return value


share.__name__ = "number in (0, 1]"
positive_number = number_above(0, False, "a number", "0.75")
defer_cost = number_above(0, True, "a defer cost", "0.3")
