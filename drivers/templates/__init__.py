"""Templates for a lab's own backends: copy one, rename the class, fill in the hooks.

Each template subclasses the device kind's base class, which keeps the shared rules (laser
safety, stage limits and timeouts, SLM frame validation). A backend only moves bytes or pixels.
Prove a new backend with its kind's contract suite in `tests/drivers/contracts` (add its set-up
as a param of the suite's fixture, or name the real device in NHFD_TEST_LASER / _STAGE / _SLM /
_CAMERA), and test its protocol the way `tests/drivers` tests the shipped ones: against a twin
that speaks it on a pseudo-terminal (see `nhfd.drivers.twins`). To select it from the
configuration, add its name to the device's backend choices in `nhfd/config.py`
(`DeviceSettings`) and a branch to `nhfd/drivers/factory.py`.

  laser_backend.py      Laser: identify, read/write one channel's enable and power
  stage_backend.py      Stage: identify, start home/moves, stop, read state, wait for the end
  slm_backend.py        SLM: write one RGB frame, report output health
  camera_backend.py     Camera: open, set exposure and gain, grab one raw frame
  navigator_backend.py  Navigator: return the latest raw axes and buttons
"""
