"""Keep ``isac_twin_msgs/msg/Detections`` out of the shared message registry
after each sensing test: every registered type must have a CDR mapping
(tests/engine/transport/test_cdr.py), which the sensing type does not have yet."""

import pytest

from engine.msgs import MESSAGE_TYPES


@pytest.fixture(autouse=True)
def _restore_message_types():
    before = dict(MESSAGE_TYPES)
    yield
    for k in set(MESSAGE_TYPES) - set(before):
        del MESSAGE_TYPES[k]
