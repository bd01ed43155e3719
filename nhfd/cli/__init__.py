"""Command-line entry points (layer L6: may import every layer below).

  main        `nhfd`: the command registry (name -> module -> one-line help); a command's module
              is imported only when that command runs, the one lazy import here besides cmd_bench
  args        shared argument parsing and `LazyCommands`, the subparsers that load on demand
  cmd_config  `nhfd config show|check`
  cmd_demo    `nhfd demo` (the daemon on the simulated bench) and `nhfd demo optics`
  cmd_scene   `nhfd scene info|render|reduce`
  cmd_dataset `nhfd dataset build|merge|show`
  cmd_model   `nhfd model build`: a scene to an evaluated, exported (and served) model
  cmd_train   `nhfd train|eval|export` (torch, onnxruntime)
  cmd_bench   `nhfd bench NAME`: its own registry of nhfd.benchmarks modules
  cmd_serve   `nhfd serve`: the daemon in the foreground (torch-free)
  cmd_replay  `nhfd replay`: a recorded session against a daemon
  cmd_laser   `nhfd laser-off|laser-guardian`: the emergency path (drivers only, no torch)
  cmd_devices `nhfd devices`
  calib       `nhfd calib capture|fit|report`
  nhfctl      `nhfctl`, the lightweight control client (config and the daemon's client only: no
              torch, numba or onnxruntime)

Every module imports at module level; what keeps `nhfd --help`, `nhfd serve` and `nhfd laser-off`
light is that main imports only the chosen command's module (and cmd_serve imports the web view,
cmd_scene the dataset envelope, only when used: the listed seams).
"""
