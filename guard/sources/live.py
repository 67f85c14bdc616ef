"""Live sources, chosen by the connection URL's scheme: `can:` is DroneCAN through python-can (imported
only then), anything else a pymavlink connection (`udpin:`, `udpout:`, `tcp:`, a serial device)."""

from __future__ import annotations

from guard.sources.link import MavlinkLink


def open_link(url: str, cfg):
    """The live source for `url` with guard's configuration `cfg` (its `link` and `can` sections)."""
    if url.startswith("can:"):
        from guard.sources.can import CanSource      # python-can and dronecan only when CAN is configured
        c = cfg.can
        return CanSource(url, gnss_node_id=c.gnss_node_id or None, imu_node_id=c.imu_node_id or None,
                         timeout_s=cfg.link.link_timeout_s, time_source=c.time_source)
    return MavlinkLink(url, cfg.link)
