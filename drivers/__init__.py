"""nhfd.drivers: one small interface per device kind, real backends, and simulated twins."""
