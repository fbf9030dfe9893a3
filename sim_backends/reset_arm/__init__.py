"""The reset arm in MuJoCo: its MjSpec model and its sim backend (docs/reset.md)."""
