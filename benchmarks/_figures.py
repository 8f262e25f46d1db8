"""What the benchmarks' figure options share: matplotlib is the optional ``plot`` extra.

A figure asked of a long run is checked before the run starts, not after it: without matplotlib,
``--figure`` / ``--plot`` / ``--plot-only`` end at once with a usage error naming the option and the
extra to install (the JSON reports need no matplotlib).
"""

from __future__ import annotations

import argparse
import importlib.util

__all__ = ["require_matplotlib"]


def require_matplotlib(parser: argparse.ArgumentParser, args: argparse.Namespace, *options: str) -> None:
    """Exit through ``parser.error`` (status 2) when one of ``options`` was given and matplotlib is absent.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The benchmark's parser (its usage line and program name go into the message).
    args : argparse.Namespace
        The parsed arguments.
    *options : str
        Attribute names of the figure options (``"figure"``, ``"plot_only"``); an option counts as
        given when its value is not ``None``.
    """
    given = [option for option in options if getattr(args, option, None) is not None]
    if given and importlib.util.find_spec("matplotlib") is None:
        flags = ", ".join("--" + option.replace("_", "-") for option in given)
        parser.error(f"{flags} needs matplotlib, which is not installed (pip install 'mvintrinsic[plot]'); "
                     "without it, leave the figure out: the JSON report needs no matplotlib")
