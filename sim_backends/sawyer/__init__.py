"""Sawyer arm: MuJoCo model from metaworld assets, vendor-side controller, sim backend, emulator."""
