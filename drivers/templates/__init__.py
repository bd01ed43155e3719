"""Templates for a lab's own backends: copy one, rename the class, fill in the hooks.

Each template subclasses the device kind's base class, which keeps the shared rules (laser
safety, stage limits and timeouts, SLM frame validation). A backend only moves bytes or pixels.
Test a new backend the way `tests/drivers` tests the shipped ones: against a twin that speaks the
device's protocol on a pseudo-terminal (see `nhfd.drivers.twins`). To select it from the
configuration, add its name to the device's backend choices in `nhfd/config.py`
(`DeviceSettings`) and a branch to `nhfd/drivers/factory.py`.

  laser_backend.py      Laser: identify, read/write one channel's enable and power
  stage_backend.py      Stage: identify, start home/moves, stop, read state, wait for the end
  slm_backend.py        SLM: write one RGB frame, report output health
  camera_backend.py     Camera: open, set exposure and gain, grab one raw frame
  navigator_backend.py  Navigator: return the latest raw axes and buttons
"""
