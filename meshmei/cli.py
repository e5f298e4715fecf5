"""Command-line entry point: ``meshmei <command>``; each command lives with the module it drives."""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["main"]

# command name -> module exposing ``add_parser(subparsers)``; the parser's ``func(args)`` runs it
COMMANDS = {
    "demo": "meshmei.story",
    "regularizers": "meshmei.demo",
    "reconstruct": "meshmei.reconstruct.core",
    "tune": "meshmei.tuning",
    "mei": "meshmei.mei.core",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshmei", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module in COMMANDS.items():
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as err:
            if err.name != module:
                raise
            continue  # command not built yet
        mod.add_parser(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, FloatingPointError) as err:
        # bad input (every meshmei error is a ValueError), files that are missing or in the way, a
        # diverging optimisation: one clear line, no traceback
        print(f"meshmei {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
