"""nhfd.models: the NHF network, training, evaluation and ONNX export.

Layer L3 (learning): imports nhfd.dataset, nhfd.holo, nhfd.optics, nhfd.scene and the vocabulary
(L0-L2), never the pipeline, the daemon or calib. Its modules import each other and torch at
module level (except `inputs`, NumPy only, and `metadata`, the standard library only); onnx
and onnxruntime load where a graph is exported or run.

Modules (import what you need; nothing heavy is imported here):
- `inputs`: what the network sees (sRGB, or sRGB + the mapped depth), built the same way by
  training and by the daemon (NumPy only);
- `net`: `NetSpec`, `NHFNet`, `build_net`, `predict` (any size: pad outside the graph, crop back),
  `to_field`;
- `loss`: `Optics`, `FocalStackLoss` (aperture + ASM focal stack, L2 + box SSIM / VGG),
  `choose_planes`, `uniform_planes`;
- `data`: `HoloData` (a dataset in memory), deterministic `batch_views`, `step_rng`, crops;
- `train`: `TrainOptions`, `train` (seeded, resumable), `load_run`;
- `evaluate`: `evaluate` (docs/physics.md's quality vs the baselines, focus check, PNG);
- `export`: `export_onnx`, `OnnxModel`, `load_model`, and `probe_model` (a candidate's first
  session and test run in a child process under a memory budget); `metadata`: what a model
  records, every field checked at parse (finite, in range, typed: `InvalidMetadata` names the
  field), and the check that refuses a model for other optics;
- `torch_model`: `TorchModel`, a model file's network rebuilt as a torch module (checked against
  the file's own graph at load): inference on a GPU without onnxruntime-gpu;
- `sizes`: the input sizes a model was checked at (against torch, or ONNX-only on tiles), their
  record in its metadata, and the refusal of a frame window of another size;
- `quantise`: static int8 export; `serving`: the graph the daemon runs; `vgg`: the optional
  perceptual loss's features;
- `half`: `convert_fp16`, the fp16 export (float16 weights and compute, float32 inputs and
  outputs, the softplus in float32), and `compare_fp16`, its check against the float model;
- `build`: `run_build`, `nhfd model build`'s stages (scene to evaluated model, resumable);
  `contact_sheet`: its held-out focal-stack picture;
- `synthetic`: a tiny dataset in the real format, for tests and smoke runs.
"""
