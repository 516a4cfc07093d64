"""Built-in CLI commands, each module a plugin that implements ``register_commands(cli)``."""
