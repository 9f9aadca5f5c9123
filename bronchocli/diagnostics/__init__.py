"""Checks of the platform itself: operation and host-sync counting, and the `bronchopose selftest` suite."""
