"""`python -m pmsmjax`: the command line, `pmsmjax.cli`."""

import sys

from pmsmjax.cli import main


if __name__ == "__main__":
    sys.exit(main())
