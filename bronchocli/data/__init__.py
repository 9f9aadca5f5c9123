"""Datasets: on-disk layout, synthetic generation, reading, trajectories, splits and caching."""
