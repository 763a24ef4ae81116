"""Procedural driving worlds seen by a simulated spinning LiDAR: pcfbench's embedded datasets."""
