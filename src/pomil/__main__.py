"""``python -m pomil`` is the ``pomil`` command."""

import sys

from pomil.cli import main

sys.exit(main())
