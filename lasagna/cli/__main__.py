"""``python -m lasagna.cli …`` is ``lasagna …``."""

import sys

from lasagna.cli import main

sys.exit(main())
