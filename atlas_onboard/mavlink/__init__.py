"""MAVLink transport: the atlas dialect, codecs, links (serial/UDP/TCP), signing and reconnects.

The only package that imports pymavlink.
"""
