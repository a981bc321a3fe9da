"""The core every room builds on: SO(3), the view graph, errors, atomic writes, configs, names, the CLI."""
