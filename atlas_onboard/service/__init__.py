"""The node as a service: start-up of ``run`` (the composition root), systemd's notify protocol, state kept
across restarts, the cores it may use, the bench checks at start, and ``install-service``."""
