"""Shared pytest setup: Dr.Jit must find a usable LLVM before mitsuba loads."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from engine._llvm import configure_llvm  # noqa: E402

configure_llvm()
