"""``python -m atlas_onboard`` is the same as the ``atlas-onboard`` console script."""

import sys

from atlas_onboard.cli import main

sys.exit(main())
