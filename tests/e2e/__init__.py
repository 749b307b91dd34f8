"""End-to-end tests: real node processes over real MAVLink on 127.0.0.1 (helpers in helpers.py)."""
