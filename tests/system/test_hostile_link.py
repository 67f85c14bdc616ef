"""The live link's fault campaign (tools/hostile_link.py), small: the paper scenario with two hostile
datagrams per genuine frame (garbage, cut frames, stray bytes, other systems, other senders) gives the
same alarm at the same GNSS sample as without them, no false alarm, and the daemon alive."""

from toolbox import load_tool


def test_hostile_frames_change_nothing_guard_does():
    tool = load_tool("hostile_link")
    frames = tool.genuine()
    clean = tool.run(0.0, 1, frames)
    bad = tool.run(2.0, 1, frames)
    assert clean["first_alarm"] == 400 and not clean["false_alarms"]
    assert bad["first_alarm"] == clean["first_alarm"] and not bad["false_alarms"] and bad["alive"], bad
    assert bad["genuine_lost"] == 0 and clean["genuine_lost"] == 0
    # every kind was sent, and what the link dropped it counted by reason
    assert set(bad["sent"]) == set(tool.KINDS)
    for reason in ("bad_frame", "partial_frame", "other_system", "other_address"):
        assert bad["skipped"][reason] > 0, bad["skipped"]
    assert bad["memory_mb"][-1] - bad["memory_mb"][0] < 20.0
