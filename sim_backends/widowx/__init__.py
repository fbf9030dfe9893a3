"""WidowX arm and task-reset mechanism: MuJoCo model, servo firmware model, sim backend, bus emulator."""
