"""The ``mmada-rl`` command line.

Each sub-command lives in its own module, which exposes ``add_parser(subparsers)``
(registering its arguments and a ``func`` default) so this file only lists them.
"""
from __future__ import annotations

import argparse
import importlib
import sys

#: sub-command modules, in the order ``--help`` lists them
_COMMANDS = (
    "mmada_rl.doctor",
    "mmada_rl.envs.cli",
    "mmada_rl.data.cli",
    "mmada_rl.tokenizers.cli",
    "mmada_rl.quickstart",
    "mmada_rl.evaluation",
    "mmada_rl.policy.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mmada-rl",
        description="Discrete-diffusion vision-language-action policies on ManiSkill3 with TorchRL.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        try:
            importlib.import_module(name).add_parser(sub)
        except ImportError as err:  # a broken install must still reach `mmada-rl doctor`
            if name == "mmada_rl.doctor":
                raise
            print(f"mmada-rl: commands of {name} are unavailable ({err}); run `mmada-rl doctor`.", file=sys.stderr)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
