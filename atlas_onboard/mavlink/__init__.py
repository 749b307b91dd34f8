"""MAVLink transport: the atlas dialect, codecs, links (serial/UDP/TCP), signing and reconnects.

The only package that imports pymavlink. Its layers, bottom up:

- :mod:`~atlas_onboard.mavlink.dialect`: ``load()`` returns the module mavgen generates from
  ``atlas.xml`` (which includes ``common.xml``), cached by hash, never committed.
- :mod:`~atlas_onboard.mavlink.framing`: the framing fast path (whole frames per read, deferred
  decoding), the one workaround of pymavlink's parser; off with ``ATLAS_ONBOARD_FRAMING=pymavlink``.
- :mod:`~atlas_onboard.mavlink.signing`: the signing key, pymavlink's signing set up on a link, the
  check before decode, the wall-clock timestamp and its persistence.
- :mod:`~atlas_onboard.mavlink.codec`: MarkerData <-> ATLAS_OBSERVATION / TUNNEL, fused poses ->
  ATLAS_FUSED_POSE; decoders raise only ``RejectionError`` (an ``AtlasError`` carrying a ``Rejection``).
- :mod:`~atlas_onboard.mavlink.autopilot`: pure functions giving the fields of
  VISION_POSITION_ESTIMATE, ODOMETRY, HEARTBEAT, TIMESYNC and SET_GPS_GLOBAL_ORIGIN (the reset
  counter is the publisher's); no pymavlink, no clock.
- :mod:`~atlas_onboard.mavlink.gate`: ``OriginBinding`` (who may send what) and ``PeerGate``
  (de-duplication, per-peer token buckets, clock skew).
- :mod:`~atlas_onboard.mavlink.link`: ``Link``, one connection with reconnects and counters, read by
  ``poll(timeout_s)`` or by its own thread (``start(handler)``).
- :mod:`~atlas_onboard.mavlink.transport`: ``MavlinkTransport``, the node's autopilot and peer links
  (implements ``atlas_onboard.node.ports.Transport``): frames, checks and delivers peer observations as
  ``core.records.Inbound`` items, decoded when the node takes them; it holds an ``AutopilotLink``
  (:mod:`~atlas_onboard.mavlink.autopilot_link`: HEARTBEAT, TIMESYNC, EKF origin, attitude, the pose sent).
"""
