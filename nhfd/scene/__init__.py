"""Gaussian splat scenes: files, cameras, the CPU rasteriser and light fields.

  gaussians       the one in-memory representation (activated float32 arrays)
  io              every scene format's loader and saver, and the format sniffing
  axes            axis conventions of splat formats, into the project's frame
  spz, sog, gltf_splat   Niantic .spz, PlayCanvas SOG, glTF KHR_gaussian_splatting
  limits          what a hostile file cannot make a reader do: the Gaussian count limit, regular
                  files only, references kept in the scene's folder, capped reads and inflation
  cameras         pinhole cameras and poses (OpenCV conventions), look-at, orbit, 6-DoF
  suggest         what a file does not state: which way is up, a camera that frames it
  raster          the tile rasteriser (numba kernels in _kernels; gsplat_backend on CUDA)
  lightfield      the translated-camera light field of docs/physics.md
  cull            reduce_scene: what a set of cameras can show (undrawn and faint splats, SH
                  bands), within a grey-level budget

Layer L1 (compute and devices): imports only the vocabulary (L0) and itself; never optics'
callers, datasets, models or the daemon. The one function-level import is raster's seam: the
numba kernels (and the optional gsplat backend) load when something is rendered, not on import.
"""
