"""Built-in measurement_system plugins (see docs/plugins.md)."""
