"""Built-in physics plugins (see docs/plugins.md)."""
