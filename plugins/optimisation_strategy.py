"""Built-in optimisation_strategy plugins (see docs/plugins.md)."""
