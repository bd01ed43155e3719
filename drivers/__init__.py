"""nhfd.drivers: one small interface per device kind, real backends, and simulated twins.

  transport    byte links: pyserial ports (exclusive, found by USB serial number) and ptys
  laser        Laser base (safety rules) + MecomLaser (FISBA READYBeam over MeCom)
  guardian     the laser guardian process, its client, `nhfd laser-off`'s other half
  stage        Stage base (motion rules) + AptStage (Thorlabs KDC101 / TDC001 over APT)
  slm          SLM base (frame validation, settle, health) + SimulatedSLM
  framebuffer  FramebufferSLM (/dev/fbN, geometry from sysfs)
  window       WindowSLM (full-screen window on a named output, vsync; needs pyglet)
  camera       Camera base (response, bursts, dark frames) + OpenCVCamera, GenICamCamera
  simcamera    SimulatedCamera and its TrueBench (imports torch: the only module here that does)
  navigator    SpaceMouse HID parsing, SpaceMouseNavigator (hidapi, optional), SimulatedNavigator
  mecom, apt   protocol frames, every constant in one place
  settings     pydantic settings for each device kind (imports nothing from nhfd)
  twins        MecomTwin and AptTwin: protocol peers on pseudo-terminals, with faults
  factory      [devices] -> drivers (simulated laser / stage = real driver + its twin)
  discovery    what is plugged in and which [devices] entry would use it (`nhfd devices`)
  templates    how a lab adds its own backend

Nothing here but simcamera imports torch, and nothing imports numba or onnxruntime; hidapi,
pyusb and pyglet are imported only where used. Software safety never replaces the lab's
hardware laser interlock.
"""
