"""WORK IN PROGRESS, not collected by pytest (the file name does not start with test_):
`rollbase drive --profile cia402` against the independent device set of cia402_devices.py.

Status (issue 24): run by hand (`python3 -m pytest interop/cia402_sessions_wip.py`), the
drive boots the twelve devices, homes the four steering axes from their random power-on
angles and turns them to rest (about 4.5 s), and tracks; but in some runs two wheels' drives
stay disabled (the devices never act on their RPDOs), so the sessions below are not reliable
yet. What was measured and what is left is in the issue's report.
"""

from test_cia402_independent import *  # noqa: F401,F403  (fixtures and helpers)
from test_cia402_independent import Drive, EDGES, WHEEL_RADIUS, platform_file  # noqa: F401
import math  # noqa: E402
import time  # noqa: E402


def test_wip_drive_homes_the_independent_devices_and_drives_as_their_positions_say(bridge, devices, tmp_path):
    host, port, _ = bridge
    before = devices.state()
    # Power-on: every steering counter reads 0, whatever the angle (incremental encoders).
    for n in (2, 4, 6, 8):
        assert before[n]["counter"] == 0, before[n]
    assert any(abs(before[n]["angle"] - EDGES[(n - 2) // 2]) > 0.2 for n in (2, 4, 6, 8))
    drive = Drive(f"socketcand://{host}:{port}/vcan0", platform_file(tmp_path), tmp_path / "drive.log")
    try:
        drive.wait_for("state: tracking")
        homed = devices.state()
        for n in (2, 4, 6, 8):
            assert homed[n]["homings"] == 1, homed[n]
            # Turned to the rest angle (0) after homing.
            assert abs(math.remainder(homed[n]["angle"], 2 * math.pi)) < 0.02, homed[n]
        wheel0 = {n: homed[n]["angle"] for n in (1, 3, 5, 7)}
        # Forward at 0.2 m/s for 2 s; an informational EMCY (error register 0) on the way.
        drive.hold(1.0, vx=0.2)
        devices.send("emcy 1 0xFF01 0")
        drive.hold(1.0, vx=0.2)
        time.sleep(1.2)  # the command timeout stops the platform
        moved = devices.state()
        travel = [(moved[n]["angle"] - wheel0[n]) * WHEEL_RADIUS for n in (1, 3, 5, 7)]
        # A steering drive loses power: its counter restarts at 0 wherever the wheel stands.
        devices.send("powercycle 4")
        drive.wait_for("device rebooted")
        drive.line({"rearm": True})
        drive.wait_for("state: tracking", count=2)
        rehomed = devices.state()
        assert rehomed[4]["homings"] == 2, rehomed[4]
        assert all(rehomed[n]["homings"] == 1 for n in (2, 6, 8)), rehomed
        drive.hold(1.0, vx=0.2)
        time.sleep(0.2)
        code, summary, log = drive.finish()
    finally:
        drive.kill()
    assert code == 0, log
    assert summary["supervisor_final_state"] == "stopped", summary
    # The informational EMCY was logged, not a fault: the only fault was the reboot.
    assert "EMCY 0xFF01" not in (summary.get("fault_reason") or "")
    assert log.count("fault: ") == 1, log
    # The base moved as the devices' own positions say: every wheel turned by the same
    # travel, and the first stretch's odometry agrees with it.
    mean = sum(travel) / 4
    assert 0.25 < mean < 0.5, travel
    assert max(travel) - min(travel) < 0.01, travel
    end = devices.state()
    total = sum((end[n]["angle"] - wheel0[n]) * WHEEL_RADIUS for n in (1, 3, 5, 7)) / 4
    x = summary["final_pose"]["x"]
    assert abs(x - total) < 0.03, (x, total, summary)


def test_wip_a_fault_emcy_stops_the_base_with_the_error_code_read_back(bridge, devices, tmp_path):
    host, port, _ = bridge
    drive = Drive(f"socketcand://{host}:{port}/vcan0", platform_file(tmp_path), tmp_path / "drive.log")
    try:
        drive.wait_for("state: tracking")
        drive.hold(0.8, vx=0.15)
        devices.send("emcy 3 0x2310 0x03")
        drive.wait_for("fault: ")
        drive.hold(0.5, vx=0.15)  # ignored: latched until re-armed
        code, summary, log = drive.finish()
    finally:
        drive.kill()
    assert code == 1, log
    reason = summary["fault_reason"]
    assert "wheel 2 rolling drive (node 3)" in reason, reason
    assert "EMCY 0x2310" in reason, reason
    # The drive's own error code, read back by SDO from the independent device.
    assert "0x603F reads 0x2310" in log, log


