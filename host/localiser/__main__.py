"""``python -m host.localiser``: train the pin localiser (see :mod:`host.localiser.train`)."""

import sys

from host.localiser.train import main

sys.exit(main())
