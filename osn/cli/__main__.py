"""``python -m osn.cli``: the same as the ``osn`` command."""

import sys

from osn.cli import main

sys.exit(main())
