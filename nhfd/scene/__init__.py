"""Gaussian splat scenes: files, cameras, the CPU rasteriser and light fields.

  gaussians   the one in-memory representation (activated float32 arrays)
  io          INRIA .ply, PlayCanvas compressed .ply and .splat: load and save
  cameras     pinhole cameras and poses (OpenCV conventions), look-at, orbit, 6-DoF
  raster      the tile rasteriser (numba kernels in _kernels)
  lightfield  the translated-camera light field of optics.md

numba is imported only when something is rendered, so `nhfd --help` stays fast.
"""
