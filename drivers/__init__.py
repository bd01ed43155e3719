"""nhfd.drivers: one small interface per device kind, real backends, and simulated twins.

  transport    byte links: pyserial ports (exclusive, found by USB serial number) and ptys
  laser        Laser base (safety rules) + MecomLaser (FISBA READYBeam over MeCom)
  guardian     the laser guardian process, its client, `nhfd laser-off`'s other half
  stage        Stage base (motion rules) + AptStage (Thorlabs KDC101 / TDC001 over APT)
  slm          SLM base (frame validation, settle, health) + SimulatedSLM
  framebuffer  FramebufferSLM (/dev/fbN, geometry from sysfs)
  navigator    SpaceMouse HID parsing, SpaceMouseNavigator (hidapi, optional), SimulatedNavigator
  mecom, apt   protocol frames, every constant in one place
  settings     pydantic settings for each device kind (imports nothing from nhfd)
  twins        MecomTwin and AptTwin: protocol peers on pseudo-terminals, with faults
  templates    how a lab adds its own backend

Nothing here imports torch, numba or onnxruntime; hidapi is imported only by the SpaceMouse
backend. Software safety never replaces the lab's hardware laser interlock.
"""
