"""The Dynamixel servo sim: one servo's firmware, a MuJoCo world of servos, an in-process bus and the bus emulator process, shared by every robot built of Dynamixel servos."""
