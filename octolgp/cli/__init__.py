"""The ``octolgp`` command line: argparse subcommands, one line and exit 2 on bad input."""

from octolgp.cli.main import main, make_parser

__all__ = ["main", "make_parser"]
