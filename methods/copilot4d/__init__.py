"""Copilot4D (Zhang et al., ICLR 2024), part 1: the point-cloud tokenizer.

A VQ-VAE that encodes a LiDAR sweep into a BEV map of discrete tokens and reconstructs it
through differentiable depth rendering on a neural feature grid (paper section 4.1, A.2.1).
The world model (discrete diffusion) is not built yet; the tokenizer is not a ``Method``.
"""
