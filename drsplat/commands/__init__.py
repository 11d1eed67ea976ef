"""CLI subcommands. Each module defines `add_parser(subparsers)` which sets `func=run`."""
