"""The research scripts' tests load their script by path (tests/scripts.py) and share tests/' helpers."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
