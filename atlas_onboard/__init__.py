"""atlas-onboard: cooperative marker-based localization for drone swarms (the Atlas method)."""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
