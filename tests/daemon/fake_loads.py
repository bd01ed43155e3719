"""What fake frame workers answer a load with: a `ModelLoaded` holding a small valid `ModelInfo`,
and a `SceneLoaded`, as the real worker does (`nhfd.worker_messages`)."""

from __future__ import annotations

from nhfd.model_info import ModelInfo
from nhfd.worker_messages import LoadModel, LoadScene, ModelLoaded, SceneLoaded

INFO = ModelInfo(inputs="rgb", wavelengths_m=(660e-9, 520e-9, 450e-9), pitch_m=8e-6,
                 aperture_shape="square", cutoff_per_px=(0.5, 0.5, 0.5), z0_m=0.006,
                 volume_m=(-0.003, 0.003), amplitude_scale=1.0, train_size_hw=(288, 512),
                 input_multiple=16, fx_px=700.0, profile="fake")


def fake_model(path: str, variant: str = "float") -> ModelLoaded:
    """A model load's report for `path`, served as it is."""
    return ModelLoaded(path=path, info=INFO, served=path, variant=variant,
                       variant_reason="a fake worker's", providers=("CPUExecutionProvider",),
                       inference="onnxruntime", inference_reason="a fake worker's",
                       device="cpu", device_reason="a fake worker's", window_hw=(288, 512),
                       checked_sizes_hw=((288, 512),), checked_sizes_recorded=True,
                       loaded_s=0.0)


def fake_scene(path: str) -> SceneLoaded:
    """A scene load's report for `path`: one Gaussian about the origin."""
    return SceneLoaded(path, 1, 1, 0, "", (0.0, 0.0, 0.0), "+z")


def fake_load(msg: LoadModel | LoadScene) -> ModelLoaded | SceneLoaded:
    """The report for load `msg`."""
    return fake_model(msg.path) if isinstance(msg, LoadModel) else fake_scene(msg.path)
