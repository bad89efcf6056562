"""``python -m BreastBiomechLib ...``: the ``breastbiomech`` command (as the Slicer panels start it
in a process of their own, where no console script may be on the path)."""

import sys

from BreastBiomechLib.cli import main

sys.exit(main())
