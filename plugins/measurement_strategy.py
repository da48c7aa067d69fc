"""Built-in measurement_strategy plugins (see docs/plugins.md)."""
