"""`nhfd serve`: the daemon that drives the bench, and its control protocol.

  protocol  JSON-RPC 2.0 framing, parameter validation and THE table of error codes
  server    the Unix-socket (and optional loopback TCP) line server
  client    the reference Python client (standard library only: `nhfctl` uses it)
  service   the daemon core: lock, guardian, devices, signals, systemd notify, the loop
  methods   the RPC methods
  jobs      bench jobs (focus, snapshot) and the scene loader, off the control loop
  views     view requests: validation and latest-wins coalescing
  bench     devices, the zero-amplitude pattern, the focus mapping, snapshots
  guardian_link  the daemon's side of the laser guardian
  notify, audit, paths  systemd notify, the audit log, runtime dirs and allowed directories
  colour    colour modes: single, capture (per-colour snapshot sequence), hw-sync
  navigation  navigator motion -> relative view moves through the set_view path
  recording session recording (JSON lines) and replay

Nothing here imports torch, numba or onnxruntime at module level.
"""
