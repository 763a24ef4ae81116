"""OccWorld (Zheng et al., 2023) on LiDAR: occupancy labelled from each sweep's rays, a scene
tokenizer (VQ-VAE over the occupancy, BEV tokens) and a spatio-temporal generative transformer
forecasting the next frame's tokens (docs/occworld.md)."""
