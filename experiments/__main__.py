"""python -m jitdyn.experiments: the same as `jitdyn experiments`."""

import sys

from jitdyn.experiments import main

sys.exit(main())
