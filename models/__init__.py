"""nhfd.models: the NHF network, training, evaluation and ONNX export."""
