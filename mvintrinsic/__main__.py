"""``python -m mvintrinsic``: the command-line interface (:func:`mvintrinsic.cli.main`)."""

import sys

from mvintrinsic.cli import main

sys.exit(main())
