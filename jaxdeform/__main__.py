"""``python -m jaxdeform``: the command-line interface (see :mod:`jaxdeform.cli`)."""

import sys

from jaxdeform.cli import main

sys.exit(main())
