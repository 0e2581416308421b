"""Subcommand modules of the CLI; each has ``register(subparsers)``."""
