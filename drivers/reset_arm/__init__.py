"""The hand's reset arm: a 7-DoF arm with a parallel-jaw gripper (docs/reset.md)."""
