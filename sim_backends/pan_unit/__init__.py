"""The pan unit in MuJoCo: its world, sim backend and bus emulator (docs/adding_a_robot.md)."""
