"""Shared pytest setup: Dr.Jit must find a usable LLVM before mitsuba loads."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from isac_twin.utils.llvm import configure_llvm  # noqa: E402

configure_llvm()


import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _no_radar_frame_left_computing():
    """A test that drops a twin with a radar frame out leaves its worker thread
    computing with Dr.Jit beside the next test (a session once aborted in
    Sionna's ``discard_invalid`` there): wait for every such frame."""
    yield
    worker = sys.modules.get("isac_twin.sensing.worker")
    if worker is not None:
        worker.wait_all()
