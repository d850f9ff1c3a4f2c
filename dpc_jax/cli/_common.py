"""Argument types and the help formatter shared by the subcommands (not a subcommand itself)."""

from __future__ import annotations

import argparse


class Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the examples' line breaks and shows the defaults."""


def image_size(text: str) -> tuple[int, int]:
    """``"240x376"`` → ``(240, 376)`` (HEIGHTxWIDTH, each at least 8 pixels)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH such as 240x376, got {text!r}") from None
    if h < 8 or w < 8:
        raise argparse.ArgumentTypeError(f"image size must be at least 8x8, got {text!r}")
    return h, w


def frame_range(text: str) -> tuple[int, int]:
    """``"0:100"`` → ``(0, 100)``: frames START (inclusive) to STOP (exclusive)."""
    try:
        start, stop = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP such as 0:100, got {text!r}") from None
    if not 0 <= start < stop:
        raise argparse.ArgumentTypeError(f"expected 0 <= START < STOP, got {text!r}")
    return start, stop
