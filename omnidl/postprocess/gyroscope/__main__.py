"""``python -m omnidl.postprocess.gyroscope FRAMES_DIR --out OUT_DIR ...`` (see :mod:`.cli`)."""
import sys

from .cli import main

sys.exit(main())
