"""hilstack sim_backends."""
