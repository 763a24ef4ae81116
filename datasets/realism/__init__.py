"""The realism report (docs/realism.md): how a generated world compares with real LiDAR, as
the harness sees both (``pcfbench synthetic compare``; compare.py). It lives beside the
dataset adapters, not in the core, because it reads the synthetic world's classes and
sensor; the generator and its physics are the synthetic adapter's
(:mod:`pcfbench.datasets.synthetic`)."""
