"""``python -m calibration.cli``: the ``twin`` command."""

import sys

from calibration.cli import main

if __name__ == "__main__":  # importing this module (as the isolation test does) runs nothing
    sys.exit(main())
