"""Built-in machine_tool plugins (see docs/plugins.md)."""
