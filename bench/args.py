"""Checks of the benchmarks' numeric arguments, shared so that each refuses a count it cannot run with a
message naming the option, before anything renders (a traceback, a NaN report or a silent 0 otherwise)."""

from __future__ import annotations

import argparse

from core.errors import QuekaroError


def check_minimums(args: argparse.Namespace, **least: int) -> None:
    """Refuse the first of `least`'s options (argparse dest names) whose value is below its minimum."""
    for dest, minimum in least.items():
        value = getattr(args, dest)
        if value is not None and value < minimum:
            raise QuekaroError(f"--{dest.replace('_', '-')} {value}: at least {minimum}")
