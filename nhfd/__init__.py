"""nhfd: neural holographic fields on a holographic display bench.

The package is layered; a module imports only from its own layer or below (tests/test_layers.py
enforces it, docs/architecture.md explains it):

  L0 vocabulary    config, spec, calibration, device_settings, and the values the frame path
                   passes: views (`View`), model_info (`ModelInfo`), frame_message
                   (`FrameMessage`, `Region`), worker_messages (the frame worker's pipe)
                   (torch-free: the daemon, the laser guardian and
                   `nhfctl` load these and nothing heavier)
  L1 compute       optics (the wave-optics core), scene (splats, cameras, rasteriser),
     and devices   drivers (installed from the repository's drivers/ folder)
  L2 data          holo (wavefront inversion), dataset (poses, shards, the builder)
  L3 learning      models (installed from models/: the network, training, export)
  L4 runtime       pipeline (frame settings, view, encoder, compute_frame, the worker process)
  L5 services      daemon (the control plane; never imports L2-L4), calib (installed from calib/)
  L6 entry points  cli, benchmarks, demos

This module holds only the version: importing `nhfd` loads nothing else.
"""

__version__ = "0.1.0"
