"""Built-in method plugins of pcfbench (registered through the ``pcfbench`` entry points)."""
