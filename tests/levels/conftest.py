"""Level test configuration: make the shared helper module beside this file (`level_samples`) importable under any
pytest import mode, and the repository root importable when PYTHONPATH is not set."""

from __future__ import annotations

import sys
from pathlib import Path

_HERE = Path(__file__).resolve().parent
_ROOT = _HERE.parents[1]
for _path in (str(_HERE), str(_ROOT)):
    if _path not in sys.path:
        sys.path.insert(0, _path)
