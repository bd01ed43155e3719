"""nhfd.calib: focal-stack capture and bench-model fitting."""
