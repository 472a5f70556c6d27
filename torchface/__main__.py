"""``python -m torchface``: the ``torchface`` command (:func:`torchface.cli.main`), for a Python whose scripts folder
is not on the PATH."""

import sys

from torchface.cli import main

if __name__ == "__main__":
    sys.exit(main())
