"""pcfbench: a plugin-based benchmark harness for LiDAR point-cloud forecasting."""

__version__ = "0.1.0"
