"""Experiments (docs/experiments.md): a sweep is a grid of cells from a TOML file, run
resumably and summarised in an ablation table and figure (sweep.py)."""
