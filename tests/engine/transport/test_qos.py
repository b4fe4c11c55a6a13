"""engine/transport/qos.py: rmw_zenoh's compact QoS chunk and rosbag2's QoS YAML."""

import pytest

from isac_twin.transport.qos import QosProfile, qos_for, rosbag2_qos_yaml


def test_compact_form_matches_rmw_zenoh_design_examples():
    # design.md: the listener's default subscription (depth 10) and the talker (depth 7)
    assert QosProfile(depth=10).to_keyexpr() == "::,10:,:,:,,"
    assert QosProfile(depth=7).to_keyexpr() == "::,7:,:,:,,"
    # rmw_zenoh's defaults (RELIABLE, VOLATILE, KEEP_LAST, 42) leave every field empty
    assert QosProfile(depth=42).to_keyexpr() == "::,:,:,:,,"
    # rmw enum values: BEST_EFFORT 2, TRANSIENT_LOCAL 1, KEEP_ALL 2
    assert QosProfile("best_effort", "transient_local", "keep_all", 3).to_keyexpr() == \
        "2:1:2,3:,:,:,,"
    for q in (QosProfile(), QosProfile("best_effort", "transient_local", "keep_all", 1)):
        assert QosProfile.from_keyexpr(q.to_keyexpr()) == q
    with pytest.raises(ValueError, match="unknown policy"):
        QosProfile.from_keyexpr("7::,:,:,:,,")
    with pytest.raises(ValueError, match="reliability"):
        QosProfile(reliability="sometimes")


def test_conventions():
    assert qos_for("/tf_static").transient_local and qos_for("/tf_static").depth == 1
    assert qos_for("/tf").depth == 100
    assert qos_for("/robot1/scan").reliability == "best_effort"
    assert qos_for("/robot1/odom") == QosProfile()
    assert qos_for("/clock").reliability == "best_effort"
    assert qos_for("/twin/tf_static").transient_local  # shared under a prefix: still latched
    assert qos_for("/isac/clock/ping") == QosProfile()


def test_rosbag2_yaml_is_a_list_of_profiles():
    text = rosbag2_qos_yaml([qos_for("/tf_static"), qos_for("/robot1/scan")])
    lines = text.splitlines()
    assert [ln for ln in lines if ln.startswith("- ")] == ["- history: 1", "- history: 1"]
    assert "  durability: 1" in lines and "  reliability: 2" in lines
    assert lines[lines.index("  deadline:") + 1:][:2] == ["    sec: 9223372036",
                                                         "    nsec: 854775807"]
    assert rosbag2_qos_yaml([]) == ""
