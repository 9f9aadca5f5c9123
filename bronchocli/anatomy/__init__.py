"""Airway anatomy: one centreline-graph model from procedural trees, graphs, volumes or meshes; lobe paths."""
