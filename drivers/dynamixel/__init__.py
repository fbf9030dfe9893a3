"""Dynamixel Protocol 2.0: control tables, packet codec, and the bus over dynamixel-sdk."""
