"""Demos (L6, entry points): what `nhfd demo` runs.

- `serve`: the daemon on the simulated bench, driven over its socket as a user drives it
  (`nhfd demo`).
- `optics`: a three-depth test target through the display chain alone (`nhfd demo optics`).
"""
