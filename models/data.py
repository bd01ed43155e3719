"""A dataset (manifest + shards) held in memory, with deterministic crops and data order.

Training needs random access to a few hundred MB at most (a 1024 x 576 view and its complex
hologram are 16 MB), so every split is read once into tensors. The data order and every random
draw of a step come from the seed, the epoch and the step alone (`step_rng`, `epoch_order`), so a
resumed run sees exactly the same crops and planes as an uninterrupted one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nhfd.dataset.build import load_manifest, shard_name
from nhfd.dataset.shard import read_shard
from nhfd.models.inputs import depth_channel, input_channels, mapped_depth


@dataclass
class Split:
    """One split's views: `rgb` [N,3,H,W] sRGB, `field` [N,3,H,W] complex64 (amplitude-scale
    units), `zh` [N,H,W] mapped depth (m, NaN off the content), `alpha` [N,H,W], `depth_in`
    [N,1,H,W] the network's depth channel (`nhfd.models.inputs.depth_channel`)."""

    indices: list[int]
    rgb: torch.Tensor
    field: torch.Tensor
    zh: torch.Tensor
    alpha: torch.Tensor
    depth_in: torch.Tensor

    def __len__(self) -> int:
        return len(self.indices)

    def inputs(self, inputs: str, views: int | slice = slice(None)) -> torch.Tensor:
        """The network inputs ("rgb" or "rgbd") of `views`: `[C, H, W]` for one index,
        `[n, C, H, W]` for a slice. Selects before concatenating: never a copy of the split."""
        if input_channels(inputs) == 3:
            return self.rgb[views]
        return torch.cat([self.rgb[views], self.depth_in[views]], dim=-3)


class HoloData:
    """The manifest and the requested splits of a dataset folder, in memory."""

    def __init__(
        self, data_dir: str | Path, splits: tuple[str, ...] = ("train", "interp", "extrap"),
        max_views: dict[str, int] | None = None,
    ) -> None:  # fmt: skip
        self.dir = Path(data_dir)
        self.manifest = load_manifest(self.dir)
        scale = (self.manifest.get("amplitude_scale") or {}).get("value")
        if not scale or not np.isfinite(scale) or scale <= 0:
            raise ValueError(
                f"{self.dir}: the manifest has no amplitude scale; the build did not finish "
                "(run `nhfd dataset build` again to complete it)"
            )
        self.amplitude_scale = float(scale)
        m = self.manifest["mapping"]
        self.a_m, self.b_m = float(m["a_m"]), float(m["b_m"])
        self.splits: dict[str, Split] = {}
        for name in splits:
            idx = list(self.manifest["splits"].get(name, []))
            if max_views and name in max_views:
                idx = idx[: max_views[name]]
            if idx:
                self.splits[name] = self._load(idx)
        if "train" in splits and "train" not in self.splits:
            raise ValueError(f"{self.dir}: no training views in the manifest's splits")
        self.camera = self._first_meta().get("camera", {})

    def _first_meta(self) -> dict:
        for name in ("train", "interp", "extrap"):
            if name in self.manifest["splits"] and self.manifest["splits"][name]:
                i = self.manifest["splits"][name][0]
                return read_shard(self.dir / shard_name(i))["meta"]
        return {}

    def _load(self, indices: list[int]) -> Split:
        rgbs, fields, zhs, alphas = [], [], [], []
        for i in indices:
            path = self.dir / shard_name(i)
            if not path.exists():
                raise FileNotFoundError(f"{path}: shard missing; finish the dataset build first")
            s = read_shard(path)
            if s["meta"].get("manifest_key") not in (None, self.manifest.get("key")):
                raise ValueError(f"{path}: written for another manifest (stale shard)")
            rgbs.append(torch.from_numpy(np.ascontiguousarray(s["rgb"], np.float32)))
            fields.append(torch.from_numpy(s["field"].astype(np.complex64)) / self.amplitude_scale)
            zhs.append(torch.from_numpy(mapped_depth(s["depth"], s["alpha"], self.a_m, self.b_m)))
            alphas.append(torch.from_numpy(s["alpha"].astype(np.float32)))
        shapes = {tuple(r.shape) for r in rgbs}
        if len(shapes) != 1:
            raise ValueError(f"{self.dir}: views of different sizes {sorted(shapes)}")
        zh = torch.stack(zhs)
        depth_in = torch.from_numpy(depth_channel(zh.numpy(), self.volume_m))[:, None]
        return Split(indices, torch.stack(rgbs), torch.stack(fields), zh, torch.stack(alphas),
                     depth_in)  # fmt: skip

    @property
    def volume_m(self) -> tuple[float, float]:
        """The dataset's hologram volume `(z_min, z_max)` about the reference plane, m."""
        v = self.manifest["settings"]["volume_m"]
        return float(v[0]), float(v[1])

    @property
    def size_hw(self) -> tuple[int, int]:
        """The views' size `(H, W)`, px."""
        s = self.manifest["settings"]
        return int(s["height_px"]), int(s["width_px"])


def epoch_order(seed: int, epoch: int, n: int) -> np.ndarray:
    """The training views' order in `epoch` (a permutation, from the seed and epoch alone)."""
    return np.random.default_rng([int(seed), 0x0DA7A, int(epoch)]).permutation(n)


def step_rng(seed: int, step: int) -> np.random.Generator:
    """The generator of every random draw of step `step` (crops, planes)."""
    return np.random.default_rng([int(seed), 0x57E9, int(step)])


def batch_views(seed: int, step: int, batch: int, n: int) -> list[int]:
    """Which training views (positions in the split) step `step` uses: the epoch order, read
    `batch` at a time; an epoch is `ceil(n / batch)` steps."""
    per_epoch = -(-n // batch)
    epoch, k = divmod(step, per_epoch)
    order = epoch_order(seed, epoch, n)
    pos = [(k * batch + j) % n for j in range(batch)]
    return [int(order[p]) for p in pos]


Edges = tuple[bool, bool, bool, bool]


def interior_edges(top: int, left: int, crop_hw: tuple[int, int], view_hw: tuple[int, int]
                   ) -> Edges:  # fmt: skip
    """(top, bottom, left, right): which edges of a crop lie inside the view, not on its border."""
    (ch, cw), (h, w) = crop_hw, view_hw
    return top > 0, top + ch < h, left > 0, left + cw < w


def random_crop(
    split: Split, views: list[int], crop_hw: tuple[int, int], rng: np.random.Generator,
    inputs: str = "rgb",
) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, Edges]:  # fmt: skip
    """Network input `[B,C,h,w]` (`inputs`), field `[B,3,h,w]` and zh `[B,h,w]` (numpy) of
    random crops, and which crop edges lie inside the view for any of them (`interior_edges`)."""
    h, w = split.rgb.shape[-2:]
    ch, cw = min(crop_hw[0], h), min(crop_hw[1], w)
    xs, fields, zhs = [], [], []
    edges = [False] * 4
    for v in views:
        top = int(rng.integers(0, h - ch + 1))
        left = int(rng.integers(0, w - cw + 1))
        edges = [a or b for a, b in zip(edges, interior_edges(top, left, (ch, cw), (h, w)),
                                        strict=True)]  # fmt: skip
        rows, cols = slice(top, top + ch), slice(left, left + cw)
        xs.append(split.inputs(inputs, v)[:, rows, cols])
        fields.append(split.field[v, :, rows, cols])
        zhs.append(split.zh[v, rows, cols])
    top_e, bottom_e, left_e, right_e = edges
    return (torch.stack(xs), torch.stack(fields), torch.stack(zhs).numpy(),
            (top_e, bottom_e, left_e, right_e))  # fmt: skip


def centre_crop(t: torch.Tensor, crop_hw: tuple[int, int]) -> torch.Tensor:
    """The centred `crop_hw` (px) of `t` [..., H, W], clipped to the view's size."""
    top, left, ch, cw = _centre(t.shape[-2:], crop_hw)
    return t[..., top : top + ch, left : left + cw]


def centre_crop_edges(view_hw: tuple[int, int], crop_hw: tuple[int, int]) -> Edges:
    """`interior_edges` of `centre_crop`."""
    top, left, ch, cw = _centre(view_hw, crop_hw)
    return interior_edges(top, left, (ch, cw), tuple(view_hw))  # type: ignore[arg-type]


def _centre(view_hw, crop_hw: tuple[int, int]) -> tuple[int, int, int, int]:
    h, w = view_hw
    ch, cw = min(crop_hw[0], h), min(crop_hw[1], w)
    return (h - ch) // 2, (w - cw) // 2, ch, cw
