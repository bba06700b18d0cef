"""``python -m lasagna …`` is ``lasagna …``."""

import sys

from lasagna.cli import main

sys.exit(main())
