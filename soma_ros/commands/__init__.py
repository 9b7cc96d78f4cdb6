"""Subcommands of the `soma` CLI. Each module exposes ``register(subparsers)``."""

import argparse

__all__ = ["documented_parser"]


def documented_parser(subparsers, name: str, help: str, doc: str) -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` is its module docstring: the first line as the description,
    the rest (from the third line on) as the epilog, with its layout kept."""
    lines = doc.splitlines()
    return subparsers.add_parser(name, help=help, description=lines[0], epilog="\n".join(lines[2:]),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
