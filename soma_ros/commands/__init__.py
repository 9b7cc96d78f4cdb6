"""Subcommands of the `soma` CLI. Each module exposes ``register(subparsers)``."""
