"""`python -m fleetmap ...` is the `fleetmap` command (for environments without the script on PATH)."""

import sys

from fleetmap.cli import main

sys.exit(main())
