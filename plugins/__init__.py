"""Built-in plugins of mtbudget, installed under the import name mtbudget_plugins."""
