"""``python -m torchtrack``: the ``torchtrack`` command."""

import sys

from torchtrack.cli import main

if __name__ == "__main__":
    sys.exit(main())
