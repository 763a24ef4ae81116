"""BEVWorld (Zhang et al., 2024) on LiDAR: a continuous BEV latent of few channels, decoded to a
3-D feature volume and rendered along rays, forecast by a latent diffusion transformer
(docs/bevworld.md)."""
