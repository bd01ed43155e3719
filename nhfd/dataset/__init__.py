"""Training datasets: poses, a resumable shard builder, and pictures of what was built.

Layer L2 (data): imports nhfd.holo, and L1 (nhfd.optics, nhfd.scene) and L0 (nhfd.config) below
it, at module level; never models, the pipeline, the daemon or calib.

  poses  the documented pose sampler (train / interpolation / extrapolation splits) and pose files
  shard  one view's record: the pure unit of work, and atomic shard files
  build  the builder: depth pass -> scene mapping -> manifest -> shards (resumable; local
         processes, --shard K/N parts and merge, or Ray tasks)
  envelope  every camera a build will render, before it is built (what the reduction keeps to)
  show   a PNG of a shard's central view and its hologram's focal stack
"""
