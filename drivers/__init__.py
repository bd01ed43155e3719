"""nhfd.drivers: one small interface per device kind, real backends, and simulated twins.

Layer L1 (design.md, "Layers"): may import the L0 vocabulary (nhfd.config, nhfd.spec,
nhfd.calibration, nhfd.device_settings) and the other L1 packages nhfd.optics and nhfd.scene
(today only simcamera does: it images through nhfd.optics); never nhfd.holo, nhfd.dataset,
nhfd.models, nhfd.pipeline, nhfd.daemon or nhfd.calib. Nothing here but simcamera imports torch,
and the factory imports simcamera only when a simulated camera is built (the daemon imports the
factory and must stay torch-free); nothing imports numba or onnxruntime. The optional
third-party backends (hidapi, pyusb, pyglet, OpenCV, harvesters) are imported only where a real
device is opened (hidapi and pyusb are dependencies; slmsuite is the `slmsuite` extra).

  device       Device: the lifecycle every kind shares (open/close, the _do_open, _do_close,
               _do_identify and _do_check_link hooks) and the one reconnect with back-off
  errors       the exceptions every driver raises (DeviceError, TransportError, LinkDown, ...)
  transport    byte links: pyserial ports (exclusive, found by USB serial number) and ptys
  laser        Laser base (safety rules) + MecomLaser (FISBA READYBeam over MeCom)
  guardian     the laser guardian process that owns the laser port, its client, and the other
               half of `nhfd laser-off`
  rundir       runtime directories (sockets, lock, tokens) and the rule that makes them
               trustworthy (standard library only)
  stage        Stage base (motion rules) + AptStage (Thorlabs KDC101 / TDC001 over APT)
  slm          SLM base (frame validation, settle, health) + SimulatedSLM
  framebuffer  FramebufferSLM (/dev/fbN, geometry from sysfs)
  window       WindowSLM (full-screen window on a named output, vsync; pyglet when opened)
  camera       Camera base (response, bursts, dark frames) + OpenCVCamera, GenICamCamera
  slmsuite     SlmsuiteSLM and SlmsuiteCamera: any slmsuite SLM or camera, nhfd's grey levels
               passed through unchanged
  trigger      TriggerLine: the SLM's frame-flip output or the camera's exposure-active line,
               and its simulated timing
  simcamera    SimulatedCamera and its TrueBench (imports torch and nhfd.optics)
  navigator    SpaceMouse HID parsing, SpaceMouseNavigator (hidapi), SimulatedNavigator
  keyswitch    a key switch on a serial port's CTS or DSR line (the arm confirmation)
  mecom, apt   protocol frames, every constant in one place
  twins        MecomTwin and AptTwin: protocol peers on pseudo-terminals, with faults; and
               KeySwitchTwin, the simulated key switch
  factory      [devices] -> drivers (a simulated laser / stage = the real driver + its twin),
               and make_bench: the one call that builds and opens a wired bench
  discovery    what is plugged in and which [devices] entry would use it (`nhfd devices`)
  templates    how a lab adds its own backend (and proves it with tests/drivers/contracts)

The settings of every device kind live in nhfd.device_settings (L0). Software safety never
replaces the lab's hardware laser interlock.
"""
