"""Built-in dataset adapters of pcfbench (registered through the ``pcfbench`` entry points)."""
