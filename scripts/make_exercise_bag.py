#!/usr/bin/env python3
"""Build the bundled exercise bag (pose goals for the lumbar brace): see brace_control/exercise.py.

    python scripts/make_exercise_bag.py demo_output/exercise [--config lumbar_brace]
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from brace_control.exercise import main  # noqa: E402

if __name__ == '__main__':
    raise SystemExit(main())
