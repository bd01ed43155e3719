"""`nhfd serve`: the daemon that drives the bench, and its control protocol.

L5 services: control plane; imports L0-L1 only (nhfd.config, spec, calibration, device_settings;
nhfd.scene, nhfd.drivers), never torch, numba or onnxruntime at module level. It starts the frame
pipeline as a separate, spawned process and talks to it over a pipe.

  service   the daemon core: start-up in a safe order, the control loop, shutdown with lasers off,
            `status`; it builds the parts below, each with what it uses, never the daemon
  dispatch  JSON-RPC lines to the methods: batches, TCP authentication, refusals while stopping,
            the audit log and the session recording per method
  methods   the RPC methods, acting on `RpcContext` (the parts and places the daemon gives them)
  errors    the recent errors `status` lists; the parts report to it through callbacks
  protocol  JSON-RPC 2.0 framing, parameter validation and THE table of error codes
  server    the Unix-socket (and optional loopback TCP) line server, with its bounds: slots,
            deadlines, buffered bytes, lines and time per pass
  arming    who may arm (the kernel's uid against daemon.arming.users / groups) and the
            optional confirmation at the bench (a key switch or a navigator button)
  scene_check  a scene file read in a child process under daemon.paths.scene_memory_mb before the
            frame worker loads it
  client    the reference Python client (standard library only: `nhfctl` uses it)
  panel     what the SLM shows: view frames, the blank (zero-amplitude) pattern, calibration
            patterns, the capture hold; every change of the panel goes through it
  bench     the non-laser devices (SLM, stage, camera), their monitor and faults; the focus
            mapping without calibration
  colour    colour modes: the panel per mode, which diodes a client may switch, the capture-mode
            snapshot sequence
  citl      a citl step's captures for the frame worker: one diode at a time, plane by plane,
            never arming; and why a bench cannot serve citl views
  views     view requests: validation and latest-wins coalescing
  navigation  navigator motion -> relative view moves through the set_view path
  guardian_link  the daemon's side of the laser guardian
  jobs      job runners: slow bench work and loads off the control loop
  recording session recording (JSON lines) and replay
  png       16-bit PNGs of camera images
  notify, audit, paths  systemd notify, the audit log, runtime dirs and allowed directories
  frame_link  the daemon's side of the frame worker: spawns `nhfd.pipeline.worker` by name,
            sends the newest view, puts returned frames on the panel, restarts a crashed worker
            (lasers off first); matches the worker's messages (`nhfd.worker_messages`) by type
            and composes the three below
  load_queue  the frame link's loads: from load jobs' threads to the worker and back, what it
            serves, the served model and scene again after a crash
  pacing    the frame link's pacing: one frame per refresh, a refinement's subframes in turn,
            the panels reused (`PanelBuffer`)
  capture_relay  citl's capture requests from the worker to the bench job and answers back;
            emission sessions' ends
"""
