"""``python -m lasagna.cli …`` is ``lasagna …``."""

from lasagna.cli import main, process_exit

process_exit(main())
