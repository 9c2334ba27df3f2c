"""python -m jitdyn.experiments: the same as `jitdyn experiments`."""

import sys

from jitdyn.experiments.reproduce import main

sys.exit(main())
