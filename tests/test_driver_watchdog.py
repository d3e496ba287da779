"""The watchdog's one rule for which joints are armed, and its deadlines."""

from __future__ import annotations

from protocol import DeviceID, Mode, commands
from reach_driver.watchdog import Watchdog

E, D = int(DeviceID.E), int(DeviceID.D)


def test_continuous_commands_arm_and_position_or_other_modes_disarm() -> None:
    w = Watchdog()
    w.note_sent([commands.current(E, 10.0), commands.velocity(D, 0.1)], now=1.0)
    assert set(w.armed) == {E, D}
    w.note_sent([commands.mode(E, Mode.CURRENT)], now=1.1)  # still continuous
    assert set(w.armed) == {E, D}
    w.note_sent([commands.position(E, 1.0), commands.mode(D, Mode.POSITION)], now=1.2)
    assert w.armed == ()


def test_expiry_trip_and_rearm() -> None:
    w = Watchdog()
    assert w.expired(10.0, 0.2, lambda dev: None) is None  # nothing armed
    w.note_sent([commands.current(E, 10.0)], now=1.0)
    assert w.expired(1.1, None, lambda dev: None) is None  # watchdog off
    assert w.expired(1.1, 0.2, lambda dev: 1.05) is None
    reason, devices = w.expired(1.3, 0.2, lambda dev: 1.25) or ("", ())
    assert reason.startswith("no command for 0.300 s") and devices == (E,)
    w.note_sent([commands.current(E, 10.0)], now=1.3)
    reason, _ = w.expired(1.45, 0.2, lambda dev: 1.0) or ("", ())
    assert reason.startswith("feedback from E (0x05) stale for 0.450 s")
    w.trip(reason)
    assert w.tripped == reason and w.armed == ()
    w.rearm()
    assert w.tripped is None


def test_link_loss_trips_only_when_armed() -> None:
    w = Watchdog()
    assert w.trip_on_link_loss() == () and w.tripped is None
    w.note_sent([commands.velocity(E, 0.1)], now=0.0)
    assert w.trip_on_link_loss() == (E,)
    assert w.tripped == "link lost while commanding 1 joint(s)" and w.armed == ()
