"""The cli tests' helpers live in _cli.py, importable from the tests as `_cli`."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
