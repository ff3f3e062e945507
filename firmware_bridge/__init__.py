"""The drone side of the wire: MAVLink 2 and NatNet codecs, links, and the SITL vehicle."""
