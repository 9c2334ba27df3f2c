"""python -m jitdyn.cli: the same as `jitdyn`."""

import sys

from jitdyn.cli.main import main

sys.exit(main())
