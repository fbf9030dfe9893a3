"""A one-joint pan unit on a Dynamixel servo (docs/adding_a_robot.md)."""
