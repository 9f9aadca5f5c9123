"""Synthetic datasets: anatomy -> trajectories -> rendered frames and poses on disk.

``pipeline.generate_dataset`` renders a dataset (VTK); ``sources`` says which
patients a config makes and generates the configured dataset when missing
without importing VTK otherwise; ``trajectories`` plans camera paths;
``writer`` writes frames, CSVs and the fingerprint atomically.
"""
