"""hilstack bus."""
