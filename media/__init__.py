"""Medium plugins, one per module; each registers itself on its last line."""
