"""Command-line entry points: `nhfd` (offline tools and the daemon) and `nhfctl` (control)."""
