"""``host localiser``: train the fixed-count Ridge pin localiser for any sensor."""
from __future__ import annotations

from host.localiser.train import add_arguments, run


def register(sub) -> None:
    """The sub-command localiser."""
    s = sub.add_parser("localiser", help="train the 133-pin (any N) Ridge localiser: "
                                         "simulated frames and/or real clips of the sensor")
    add_arguments(s)
    s.set_defaults(func=run)
