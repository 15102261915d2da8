"""Messages one backend reads reach the others: a CRSF receiver's link statistics become a
MAVLink RADIO_STATUS that a pymavlink ground station decodes."""

from __future__ import annotations

import os

from helpers import wait_for
from mavlink_peer import MavPeer

from backends.crsf.backend import CrsfBackend
from backends.crsf.frames import LinkStatistics, encode
from backends.crsf.options import CrsfOptions
from backends.mavlink.backend import MavlinkBackend
from backends.mavlink.options import MavlinkOptions
from gateway.backend import GatewayContext
from gateway.dispatcher import Dispatcher
from gateway.model import LinkStats

WAIT = 10.0


def _signed(byte: int) -> int:
    return byte - 256 if byte > 127 else byte


def test_receiver_link_statistics_reach_a_ground_station_as_radio_status() -> None:
    master, slave = os.openpty()
    gcs = MavPeer(255, 190)
    mavlink = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{gcs.port}"]))
    crsf = CrsfBackend(CrsfOptions(url=os.ttyname(slave)), name="elrs")
    d = Dispatcher([crsf, mavlink])
    crsf.attach(GatewayContext(emit=d.dispatch))
    try:
        assert d.start() == []
        # The receiver (the pty's other end) reports: uplink -67 dBm, SNR 8 dB, LQ 95 %;
        # downlink -71 dBm, SNR 5 dB.
        stats = LinkStatistics(-67, -70, 95, 8, 0, 5, 2, -71, 99, 5)
        # pyserial flushes a port's input as it opens it: write once the engine has it open
        assert wait_for(lambda: crsf.engine.connected)
        os.write(master, encode(stats))
        got = gcs.wait_for("RADIO_STATUS", timeout=WAIT)
    finally:
        d.close()
        gcs.close()
        os.close(master)
        os.close(slave)
    assert got, "no RADIO_STATUS reached the ground station"
    rs = got[0]
    # QGC reads a non-SiK radio's rssi/remrssi/noise as signed dBm.
    assert (_signed(rs.rssi), _signed(rs.remrssi)) == (-67, -71)
    assert (_signed(rs.noise), _signed(rs.remnoise)) == (-75, -76)  # RSSI − SNR
    assert rs.txbuf == 100 and rs.get_srcSystem() == 1
    assert crsf.stats()["link_stats"] >= 1


def test_unknown_link_figures_are_uint8_max() -> None:
    from backends.mavlink.translate import radio_status

    rs = radio_status(LinkStats(rssi_dbm=-200.0, link_quality_pct=50))
    assert (rs.rssi, rs.remrssi, rs.noise, rs.remnoise) == (256 - 128, 255, 255, 255)
    assert radio_status(LinkStats(rssi_dbm=0.0)).rssi == 256 - 2  # never 255 for a value
