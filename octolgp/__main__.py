"""``python -m octolgp``: the command line."""

import sys

from octolgp.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
