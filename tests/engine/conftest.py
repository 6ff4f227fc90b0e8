import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from .engine_helpers import cfg_factory  # noqa: E402,F401  (fixture)
