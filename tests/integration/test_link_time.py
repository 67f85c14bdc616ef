"""A live link whose autopilot stamps GPS_RAW_INT in UNIX time and RAW_IMU from boot (MAVLink lets the
sender choose): the fixes come out on the boot clock, joined by their arrival, and that is logged."""

import logging
import time

import guard.sources.mavlink  # noqa: F401  (sets MAVLINK20=1 before pymavlink is imported)

from guard.model.samples import GnssFix, ImuSample
from integration.test_link_hostile import LAT, LON, collect, open_link, sender, udp_socket

UNIX_US = 1_750_000_000_000_000


def test_fixes_in_unix_time_come_out_on_the_boot_clock(caplog):
    link, addr = open_link()
    sock, mav = udp_socket(), sender()
    caplog.set_level(logging.WARNING, logger="guard.sources.link")
    try:
        boot0 = 5_000_000
        for k in range(60):                         # 3 s: IMU at 50 Hz, a fix at 10 Hz in UNIX time
            t = boot0 + k * 20_000
            msg = mav.raw_imu_encode(t, 0, 0, -1000, 0, 0, 0, 200, 0, 400)
            sock.sendto(bytes(msg.pack(mav)), addr)
            if k % 5 == 0:
                fix = mav.gps_raw_int_encode(UNIX_US + t, 3, LAT, LON, 187000, 100, 150, 500, 0, 12)
                sock.sendto(bytes(fix.pack(mav)), addr)
            time.sleep(0.02)
        got = collect(link, lambda s: sum(isinstance(x, GnssFix) for x in s) >= 12)
    finally:
        sock.close()
        link.close()
    fixes = [s for s in got if isinstance(s, GnssFix)]
    imu = [s for s in got if isinstance(s, ImuSample)]
    assert len(fixes) == 12 and imu
    # each fix within the link's jitter of the IMU sample sent with it, on the boot clock
    assert all(abs(f.t_us - (boot0 + 100_000 * i)) < 50_000 for i, f in enumerate(fixes)), \
        [f.t_us - boot0 for f in fixes]
    said = [r.getMessage() for r in caplog.records if "UNIX time" in r.getMessage()]
    assert len(said) == 1, said
