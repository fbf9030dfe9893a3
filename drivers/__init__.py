"""hilstack drivers."""
