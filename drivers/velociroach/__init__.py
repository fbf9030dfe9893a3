"""VelociRoACH hexapod millirobot: radio-link driver (XBee 802.15.4 + MAVLink v2)."""
