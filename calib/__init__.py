"""nhfd.calib: focal-stack capture and bench-model fitting.

Layer L5 (services): may import L0-L4 and the daemon's client and protocol (it drives a running
daemon); the daemon never imports it. Everything imports at module level.

  patterns     the calibration holograms (dots, gratings, flats) from a small PatternSpec
  data         the capture folder's format (manifest and file names) and reading it back
  capture      capturing a focal-stack data set through a BenchIO (the twins, or a daemon)
  geometry     camera geometry from the dot hologram
  focus        depth mapping and phase sign from the dots' focal stacks
  response     the phase response and per-colour intensity from gratings
  bench_model  the differentiable bench model and the depth mapping fitted through it
  fit          the whole fit: a capture -> a `nhfd.calibration.Calibration`
  report       PNGs of a capture against its fit; of a learn folder, the learned bench
               against the parametric one on held-out captures (`write_learned_report`)
  citl         the camera in refinement's loop (`CameraLoop`): show, capture at the content's
               planes, map onto the SLM grid through the calibration; never arms
  learn        `nhfd calib learn`: capture a training set through `CameraLoop`, fit the learned
               bench on the calibration, write its weights, captures and scores (`fidelity`)
  sim          the simulated bench calibrated once per twin and panel, and its armed devices
               (`nhfd refine --sim`, `nhfd bench quality`)
"""
