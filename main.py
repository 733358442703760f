"""softfem command line: simulate, export, view, bench, scenes, help.

    python main.py help

The commands live in app/cli.py; once installed (`pip install .`) the same
command line is also the `softfem` command.
"""

import sys

from app.cli import build_parser, main  # noqa: F401  (tests and tools call main.main)

if __name__ == "__main__":
    sys.exit(main())
