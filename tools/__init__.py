"""hilstack tools."""
