"""Picture scripts: figures of the scenes and results for the README and docs."""
