"""python -m client.experiments: the same as `jitdyn experiments`."""

import sys

from client.experiments import main

sys.exit(main())
