"""The frame pipeline: a view of the scene -> the SLM's coded grey region.

L4 runtime; imports L0-L3, never nhfd.daemon or nhfd.calib. The daemon spawns `worker` as its
own process by name and talks to it over a pipe (`nhfd.daemon.frame_link`); the tests,
`nhfd bench pipeline` and `nhfd demo` call the rest directly.

  frame     `compute_frame(view, scene, model, encoder) -> Frame`: the whole data flow, its
            stages in order (render, inference, propagation, coding), each timed
  settings  `FrameSettings` and its one constructor `frame_settings(config, metadata,
            calibration)` (a calibration's part: `with_calibration`); the panel `Region` a
            frame changes, the zero pattern around it
  view      a view -> the render camera (`SceneFrame`, `Scene`, `render_camera`), and whether
            it lies inside the model's trained poses (`envelope_warnings`)
  encoder   `Encoder`: the reference-plane field -> the SLM plane (`nhfd.optics.region`) ->
            double-phase coding -> calibrated phase -> grey, uint8
  device    `daemon.frames.device` -> a torch device (`resolve_device`), the pinned
            asynchronous host copy of a CUDA frame (`HostCopy`), CUDA-event stage times
            (`StageClock`)
  refine    frames better than the network's: `exact` (the view's light-field inversion),
            `sgd` (the SLM phase optimised through the calibrated bench model, `BenchForward`),
            `citl` (the camera in the loop, through a `Capture`), K subframes; `refine_view`
  citl      the camera in the loop's worker half: a `Capture` served by the daemon's bench
            over the pipe (`RemoteCapture`), captures -> the window's grid (`captured_window`)
  tune      `nhfd model tune`: a scene's exported model trained further through one bench's
            frozen model (`tune_model`, the frame path written differentiably:
            `DifferentiableCoding`), checkpointed and resumable; the tuned ONNX records the
            calibration it fits (`tuned_for`)
  warmup    the frame path's numba kernels compiled and cached before the first frame
            (`nhfd warmup`)
  worker    the frame worker process: `worker_main`, model loading and checking (`open_model`,
            `check_inference`, `ModelUnfit`; a load reported as a `ModelLoaded`), the frame cache
"""
