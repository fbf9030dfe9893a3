"""WidowX 250 arm and its task-reset mechanism over Dynamixel Protocol 2.0."""
