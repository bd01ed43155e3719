"""`nhfd bench ...`: benchmarks as user commands (figures for the README come from here).

Layer L6 (entry points): may import every layer below, and nhfd.cli.args. Each module is one
benchmark with `register(subparsers)`, imported by `nhfd.cli.cmd_bench`'s registry only when it
runs, so each imports what it measures at module level.

  optics    angular-spectrum propagation vs the bare FFT pair; padding accuracy
  render    CPU splat rendering vs NumPy compositing
  holo      wavefront inversion: seconds per full-colour example
  tradeoff  network size vs latency vs held-out quality (trains, exports, quantises)
  pipeline  view-change-to-SLM latency per stage
  load      the daemon's status latency and memory under a set_view storm; idle CPU
  safety    time from each fault to every laser off
  geometry  calibration's dot geometry vs OpenCV; the bench model's warp and SSIM vs kornia
  triggers  a simulated calibration capture with and without hardware triggers
  distributed  2 local workers vs 1: dataset build (processes, Ray) and training (torchrun)
  quality   speed against captured quality of the frame tiers (exact, sgd, citl; K)
  refine    ms per sgd iteration per device at the panel's size
  machine   what machine a benchmark ran on
"""
