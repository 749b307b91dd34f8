"""MAVLink transport: the atlas dialect, codecs, links (serial/UDP/TCP), signing and reconnects.

The only package that imports pymavlink. Its layers, bottom up:

- :mod:`~atlas_onboard.mavlink.dialect`: ``load()`` returns the module mavgen generates from
  ``atlas.xml`` (which includes ``common.xml``), cached by hash, never committed.
- :mod:`~atlas_onboard.mavlink.codec`: MarkerData <-> ATLAS_OBSERVATION / TUNNEL, fused poses ->
  ATLAS_FUSED_POSE; decoders raise only ``RejectionError(reason)``.
- :mod:`~atlas_onboard.mavlink.autopilot`: pure functions giving the fields of
  VISION_POSITION_ESTIMATE, ODOMETRY, HEARTBEAT, TIMESYNC and SET_GPS_GLOBAL_ORIGIN (the reset
  counter is the publisher's); no pymavlink, no clock.
- :mod:`~atlas_onboard.mavlink.gate`: ``PeerGate`` (de-duplication, per-peer token buckets, clock skew).
- :mod:`~atlas_onboard.mavlink.link`: ``Link``, one connection with signing, reconnects and counters,
  read by ``poll(timeout_s)`` or by its own thread (``start(handler)``).
- :mod:`~atlas_onboard.mavlink.transport`: ``MavlinkTransport``, the node's autopilot and peer links
  (implements ``atlas_onboard.node.Transport``).
"""
