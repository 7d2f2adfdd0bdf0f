"""The ``lunarnav`` command: one subcommand per pipeline stage.

Each stage's ``cli.py`` exposes ``register(subparsers)``, which adds its sub-parser and sets
``func`` (a callable taking the parsed arguments and returning an exit code). User-facing
errors are printed as one line on stderr with exit code 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from lunarnav_ml import __version__
from lunarnav_ml.errors import REPORTED_ERRORS

# Stage modules whose ``register`` adds a subcommand, in the order ``--help`` lists them.
STAGE_CLI_MODULES = (
    "lunarnav_ml.synth.cli",  # lunarnav synth
    "lunarnav_ml.training.cli",  # lunarnav train, lunarnav detect, lunarnav average
    "lunarnav_ml.eval.cli",  # lunarnav eval
    "lunarnav_ml.realdata.cli",  # lunarnav import-real
    "lunarnav_ml.export.cli",  # lunarnav export, lunarnav bench
    "lunarnav_ml.runtime.cli",  # lunarnav localize
    "lunarnav_ml.demo",  # lunarnav demo
)


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors exit with code 2 and one line (argparse's default)."""


def build_parser(modules: Sequence[str] = STAGE_CLI_MODULES) -> argparse.ArgumentParser:
    """Build the ``lunarnav`` parser with every stage's subcommands."""
    parser = _Parser(prog="lunarnav", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"lunarnav {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    subparsers.required = True
    for name in modules:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lunarnav`` console script."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and not getattr(args, "forwards_args", False):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if extra:  # a forwarding subcommand (``train``) takes what argparse did not know
        args.cli_args = list(args.cli_args or []) + extra
    try:
        code = args.func(args)
    except REPORTED_ERRORS as err:
        print(f"lunarnav {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"lunarnav {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
