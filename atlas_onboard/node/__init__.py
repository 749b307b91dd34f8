"""The running node: one loop owning the listener, the graph and the publisher, fed by bounded queues.

- :mod:`.ports`: what the node needs from its transport and its cameras (protocols, in full);
- :mod:`.setup`: the blocks one world file gives the node (graph, listener, lookups), built at start and
  on SIGHUP, and the world file re-read;
- :mod:`.intake`: the camera and link threads' side (the inbox, the parking buffer, the peer links' pause);
- :mod:`.loop`: :class:`~atlas_onboard.node.loop.Node`, the loop (one thread): what is evaluated when;
- :mod:`.output`: evaluation, the autopilot's pose, the EKF, fused poses, telemetry, lateness;
- :mod:`.refine`: live map refinement from the observations the node accepts.
"""
