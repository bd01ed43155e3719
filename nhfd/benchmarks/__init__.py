"""`nhfd bench ...`: benchmarks as user commands (figures for the README come from here)."""
