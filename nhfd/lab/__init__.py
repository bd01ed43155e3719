"""The bench in the lab's own tools (L6): optional integrations over the daemon's JSON-RPC client.

- `nhfd.lab.bluesky`: ophyd devices for Bluesky (`pip install nhfd[bluesky]`): the focus as a
  positioner, the view as a settable device, the camera as a detector, the laser powers as
  read-only signals; `connect()` builds them over `nhfd.daemon.client.Client`.
- `nhfd.lab.bluesky_demo`: a Bluesky focus scan on the simulated bench (a daemon in this process)
  and its plot, `python -m nhfd.lab.bluesky_demo --out docs/figures/bluesky_focus_scan.png`.

Only the optional path imports these modules: they import ophyd and bluesky at module level.
Nothing here arms the lasers; a person does, over the daemon's Unix socket.
"""
