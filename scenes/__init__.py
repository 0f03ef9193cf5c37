"""Built-in scene files (TOML), loadable by name."""
